//! Services: calls with a reply, progress on the way, and cancel, between
//! nodes or inside one. The wire is [`crate::wire::service`]; what a call
//! and a server decide is [`crate::proto::call`] and
//! [`crate::proto::service`]; `docs/services.md` has the whole story.

use std::collections::HashMap;
use std::future::Future;
use std::marker::PhantomData;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

use bytes::Bytes;
use futures_util::FutureExt;
use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::channel::{Channel, Namespace};
use crate::discovery::MemberView;
use crate::error::{Error, NameError, Result};
use crate::name::resolve_name;
use crate::proto::call::{Call, Event};
use crate::proto::service::{Admit, Counts, Limits, Server as Admission};
use crate::runtime::services::{Answerer, LocalServer, Pending, ReplyTo, RequestTx};
use crate::runtime::{ChannelState, Inner};
use crate::subscription::{CallbackSubscription, Message};
use crate::sync::lock;
use crate::wire::service::{self as wire, code, CallId, Frame};
use crate::wire::{self as codec, DecodeError};
use crate::Schema;
use pulicast_discovery::wire::TypeInfo;

/// How long a call waits for its reply unless told otherwise
/// ([`Client::with_deadline`], [`Client::call_within`]).
pub const DEFAULT_DEADLINE: Duration = Duration::from_secs(5);

/// How long the servers a client found serve its calls before it reads
/// discovery again (a server gone meanwhile is seen by the call).
const TARGETS_FRESH: Duration = Duration::from_millis(100);

/// How often a call in flight asks discovery whether its server is still
/// there (discovery sees a crash within about 400 ms).
const SERVER_CHECK: Duration = Duration::from_millis(200);

/// The longest failure message sent; longer ones are cut.
const MAX_FAULT_MESSAGE: usize = 1024;

/// A server's own failure, sent back to the caller as its
/// [`Error::CallFailed`]: a code (use [`Fault::APPLICATION`] and above;
/// those below are pulicast's, as named by the constants here) and a
/// message for a person.
///
/// ```
/// use pulicast::Fault;
/// let f = Fault::new(1001, "no path to the goal");
/// assert_eq!(f.to_string(), "no path to the goal (code 1001)");
/// assert_eq!(Fault::msg("out of range").code, Fault::APPLICATION);
/// ```
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message} (code {code})")]
pub struct Fault {
    /// The code.
    pub code: u16,
    /// What went wrong.
    pub message: String,
}

impl Fault {
    /// The request did not decode as the server's request type.
    pub const BAD_REQUEST: u16 = code::BAD_REQUEST;
    /// The handler panicked.
    pub const PANICKED: u16 = code::PANICKED;
    /// The caller cancelled the call.
    pub const CANCELLED: u16 = code::CANCELLED;
    /// The call's deadline passed at the server.
    pub const DEADLINE: u16 = code::DEADLINE;
    /// The call ran, and its answer was too large to keep for a
    /// retransmitted request (it is not run again).
    pub const LOST: u16 = code::LOST;
    /// The reply did not encode as the server's reply type.
    pub const BAD_REPLY: u16 = code::BAD_REPLY;
    /// The server left the fleet, or failed, before it answered: a
    /// caller's own conclusion from discovery, never sent.
    pub const SERVER_GONE: u16 = code::SERVER_GONE;
    /// A bridge could not run the call on the server's site: the site is
    /// out of reach, the server is not there (any more), busy, or refused
    /// the bridge's call (its types or keys).
    pub const UNREACHABLE: u16 = code::UNREACHABLE;
    /// The first code for handlers' own failures (and what [`Fault::msg`]
    /// uses).
    pub const APPLICATION: u16 = code::APPLICATION;

    /// A failure with a code of the handler's choosing.
    pub fn new(code: u16, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
        }
    }

    /// A failure with the first application code.
    pub fn msg(message: impl Into<String>) -> Self {
        Self::new(code::APPLICATION, message)
    }
}

impl From<String> for Fault {
    fn from(message: String) -> Self {
        Self::msg(message)
    }
}

/// A pulicast error inside a handler (a progress message that would not
/// encode, say) fails the call with its text, so `?` works there.
impl From<Error> for Fault {
    fn from(e: Error) -> Self {
        Self::msg(e.to_string())
    }
}

impl From<&str> for Fault {
    fn from(message: &str) -> Self {
        Self::msg(message)
    }
}

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

/// A handler with its types erased: request message in, reply message out.
type Runner =
    Box<dyn Fn(Bytes, CallContext<()>) -> BoxFuture<Result<Vec<u8>, Fault>> + Send + Sync>;

/// What a running call shares with its handler's [`CallContext`].
struct Running {
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
struct ServerCore {
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
type Targets = Box<dyn Fn(&str) -> bool + Send + Sync>;

impl ServerCore {
    fn send(&self, frame: &Frame<'_>, to: ReplyTo) {
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

/// The longest prefix of `text` of at most `max` bytes that ends on a
/// character boundary.
fn cut(text: &str, max: usize) -> &str {
    if text.len() <= max {
        return text;
    }
    let mut end = max;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    &text[..end]
}

/// Announcements a server or client holds in discovery, let go on drop.
struct Held {
    inner: Weak<Inner>,
    held: Vec<(Arc<ChannelState>, bool)>,
}

impl Held {
    fn new(inner: &Arc<Inner>) -> Self {
        Self {
            inner: Arc::downgrade(inner),
            held: Vec::new(),
        }
    }

    /// Announces `channel` as published (`publishes`) or subscribed, with
    /// type `ty` if given.
    fn hold(
        &mut self,
        inner: &Inner,
        channel: Arc<ChannelState>,
        publishes: bool,
        ty: Option<TypeInfo>,
    ) {
        let mut changed = channel.hold(publishes);
        if let Some(ty) = ty {
            changed |= channel.note_type(ty.fingerprint, || ty.clone());
        }
        if changed {
            inner.announce_change();
        }
        self.held.push((channel, publishes));
    }
}

impl Drop for Held {
    fn drop(&mut self) {
        let changed = self.held.drain(..).fold(false, |changed, (c, publishes)| {
            c.release(publishes) | changed
        });
        if let Some(inner) = self.inner.upgrade().filter(|_| changed) {
            inner.announce_change();
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

/// A service's full name and request channel from a name as given
/// (`plan`, `../rover2/plan`), resolved in `ns`.
fn service_names(ns: &Namespace, name: &str) -> Result<(String, String)> {
    if name.contains(wire::TARGET_MARK) {
        return Err(Error::InvalidName {
            name: name.to_string(),
            reason: NameError::Reserved,
        });
    }
    let full = resolve_name(name, ns.path())?;
    let request = wire::request_channel_of(&full);
    // Checked as any channel name (and so the service's name with it).
    resolve_name(&request, "")?;
    Ok((full, request))
}

/// A server being made, with options: made by [`Namespace::server`].
#[must_use = "a server serves once one of its serve methods is called"]
#[derive(Debug)]
pub struct ServerBuilder {
    ns: Namespace,
    name: String,
    limits: Limits,
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

fn decode_request<Req: DeserializeOwned + Schema>(bytes: &[u8]) -> Result<Req, Fault> {
    codec::decode_native::<Req>(bytes).map_err(|e| {
        Fault::new(
            code::BAD_REQUEST,
            format!("the request is not a {}: {e}", Req::SCHEMA.name),
        )
    })
}

fn encode_reply<Rep: Serialize + Schema>(reply: &Rep) -> Result<Vec<u8>, Fault> {
    let mut out = Vec::new();
    codec::encode_native(reply, &mut out)
        .map_err(|e| Fault::new(code::BAD_REPLY, e.to_string()))?;
    Ok(out)
}

/// The type announced for `T`; none for raw bytes, which carry none.
fn type_info<T: Schema + ?Sized>() -> Option<TypeInfo> {
    (!codec::is_raw_bytes(T::SCHEMA)).then(codec::type_info_of::<T>)
}

fn is_unit<T: Schema + ?Sized>() -> bool {
    matches!(T::SCHEMA.ty, postcard_schema::schema::DataModelType::Unit)
}

impl Namespace {
    /// Starts making a server of service `name` in this namespace, to set
    /// its options (see [`ServerBuilder`]).
    pub fn server(&self, name: &str) -> ServerBuilder {
        ServerBuilder {
            ns: self.clone(),
            name: name.to_string(),
            limits: Limits::default(),
        }
    }

    /// Serves `name` in this namespace with an async handler: each request
    /// of type `Req` is answered with the handler's `Rep` or its [`Fault`].
    /// Several nodes may serve one name; one node serves it once.
    ///
    /// ```
    /// use pulicast::Fault;
    /// # #[tokio::main(flavor = "multi_thread", worker_threads = 2)]
    /// # async fn main() -> pulicast::Result<()> {
    /// # let port = pulicast::unused_port()?;
    /// let node = pulicast::Node::new("planner")
    ///     .namespace("rover1")
    ///     .interface(std::net::Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start()
    ///     .await?;
    /// let _server = node.serve("double", |x: i64| async move {
    ///     x.checked_mul(2).ok_or(Fault::msg("too large"))
    /// })?;
    /// // A call from this node itself skips the network.
    /// let client = node.client::<i64, i64>("double")?;
    /// assert_eq!(client.call(&21).await?, 42);
    /// assert!(matches!(
    ///     client.call(&i64::MAX).await,
    ///     Err(pulicast::Error::CallFailed { code: 1000, .. })
    /// ));
    /// # Ok(()) }
    /// ```
    pub fn serve<Req, Rep, F, Fut>(&self, name: &str, handler: F) -> Result<Server>
    where
        Req: DeserializeOwned + Schema + Send + 'static,
        Rep: Serialize + Schema + 'static,
        F: Fn(Req) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Rep, Fault>> + Send + 'static,
    {
        self.server(name).serve(handler)
    }

    /// Serves `name` with a blocking handler (see
    /// [`ServerBuilder::serve_blocking`]).
    pub fn serve_blocking<Req, Rep, F>(&self, name: &str, handler: F) -> Result<Server>
    where
        Req: DeserializeOwned + Schema + Send + 'static,
        Rep: Serialize + Schema + 'static,
        F: Fn(Req) -> Result<Rep, Fault> + Send + Sync + 'static,
    {
        self.server(name).serve_blocking(handler)
    }

    /// A client of service `name` (`plan`, or `plan@node` to call only
    /// that node's server), with request type `Req` and reply type `Rep`.
    pub fn client<Req, Rep>(&self, name: &str) -> Result<Client<Req, Rep>>
    where
        Req: Serialize + Schema,
        Rep: DeserializeOwned + Schema,
    {
        self.client_with_progress::<Req, Rep, ()>(name)
    }

    /// Like [`Namespace::client`], for a service whose handlers send
    /// progress messages of type `P` ([`OngoingCall::progress`]).
    pub fn client_with_progress<Req, Rep, P>(&self, name: &str) -> Result<Client<Req, Rep, P>>
    where
        Req: Serialize + Schema,
        Rep: DeserializeOwned + Schema,
        P: DeserializeOwned + Schema,
    {
        let types = Types {
            request: type_info::<Req>(),
            reply: type_info::<Rep>(),
            progress: (!is_unit::<P>()).then(type_info::<P>).flatten(),
        };
        Ok(Client {
            raw: RawClient::new(self, name, types)?,
            _types: PhantomData,
        })
    }

    /// A client that sends and receives messages as bytes (fingerprint
    /// first), for tools that know the types from discovery only.
    pub fn raw_client(&self, name: &str) -> Result<RawClient> {
        RawClient::new(self, name, Types::default())
    }
}

#[derive(Debug, Default, Clone)]
struct Types {
    request: Option<TypeInfo>,
    reply: Option<TypeInfo>,
    progress: Option<TypeInfo>,
}

/// Where a call goes.
#[derive(Clone)]
enum Target {
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

struct ClientCore {
    inner: Arc<Inner>,
    service: String,
    target: Option<String>,
    channel: Arc<ChannelState>,
    /// Where its requests leave from.
    request: Arc<RequestTx>,
    /// The servers last found, and when.
    targets: Mutex<Option<(Instant, Vec<Target>)>>,
    types: Types,
    next: AtomicUsize,
    _held: Held,
}

impl Drop for ClientCore {
    fn drop(&mut self) {
        self.inner.release_answers(&self.channel);
    }
}

/// A client whose messages are bytes: made by [`Namespace::raw_client`].
/// Typed clients ([`Client`]) are built on it.
#[derive(Clone)]
pub struct RawClient {
    core: Arc<ClientCore>,
    deadline: Duration,
}

impl std::fmt::Debug for RawClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RawClient")
            .field("service", &self.core.service)
            .field("target", &self.core.target)
            .finish_non_exhaustive()
    }
}

/// One server's answer to [`Client::call_all`].
#[derive(Debug)]
pub struct Answer<T> {
    /// The server node.
    pub node: String,
    /// Its reply, or why there is none.
    pub result: Result<T>,
}

impl RawClient {
    fn new(ns: &Namespace, name: &str, types: Types) -> Result<Self> {
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
                service,
                target,
                channel,
                request: request_tx,
                targets: Mutex::new(None),
                types,
                next: AtomicUsize::new(0),
                _held: held,
            }),
            deadline: DEFAULT_DEADLINE,
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
            None => self.core.service.clone(),
        }
    }

    /// The nodes that serve the service now (this node first if it does),
    /// as discovery knows them.
    pub fn servers(&self) -> Vec<String> {
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
    fn no_server_in_time(&self, e: Error) -> Error {
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
    fn check(&self, target: &Target) -> Result<()> {
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

    fn launch(
        &self,
        target: Target,
        message: &[u8],
        deadline: Instant,
        within: Duration,
    ) -> Result<RawCall> {
        let inner = &self.core.inner;
        let id = inner.next_call();
        let node = target.node(inner.name()).to_string();
        let left = deadline.saturating_duration_since(Instant::now());
        let mut frame = Vec::new();
        Frame::Request {
            call: id,
            target: &node,
            // At least 1: 0 would mean no deadline.
            deadline_ms: u32::try_from(left.as_millis()).unwrap_or(u32::MAX).max(1),
            message,
        }
        .encode(&mut frame)
        .map_err(|e| Error::config("service call", e.to_string()))?;
        let now = Instant::now();
        let (answerer, local, server) = match &target {
            Target::Local(server) => (Answerer::Local, Some(Arc::clone(server)), None),
            Target::Remote(member, address) => {
                (Answerer::At(*address), None, Some((member.key, now)))
            }
        };
        let pending = Pending::new(Call::new(id, frame, now, deadline), answerer);
        inner.add_call(id, Arc::clone(&pending));
        let mut call = RawCall {
            client: self.clone(),
            pending,
            id,
            node,
            local,
            server,
            ended: false,
            replied: false,
            gone: false,
            reads: false,
            within,
        };
        // The request leaves now (a request that can't be sent fails the
        // call at once); it is sent again while the call is awaited.
        let first = lock(&call.pending.state).call.poll_transmit(now);
        if let Some(request) = first {
            if let Err(e) = call.send(&request) {
                call.end();
                return Err(e);
            }
        }
        Ok(call)
    }

    /// Starts a call of `message` (fingerprint first): waits for a server
    /// (within the deadline), checks it can answer, sends the request.
    pub async fn start(&self, message: &[u8], within: Duration) -> Result<RawCall> {
        let deadline = Instant::now() + within;
        let target = self.pick(deadline).await?;
        self.check(&target)?;
        self.launch(target, message, deadline, within)
    }

    /// Like [`RawClient::start`], blocking the thread while it waits for
    /// a server.
    pub fn start_blocking(&self, message: &[u8], within: Duration) -> Result<RawCall> {
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

/// A call in flight whose messages are bytes: from [`RawClient::start`].
/// Dropping it before its end cancels it (the server's handler is told).
pub struct RawCall {
    client: RawClient,
    pending: Arc<Pending>,
    id: CallId,
    node: String,
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
    within: Duration,
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
enum Step {
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

    fn send(&self, frame: &[u8]) -> Result<()> {
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

    fn end(&mut self) {
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

/// What a typed client takes and gives, as a type.
type Signature<Req, Rep, P> = fn(&Req) -> (Rep, P);

/// A typed client of a service: made by [`Namespace::client`] (or
/// [`Namespace::client_with_progress`] for progress of type `P`).
///
/// A call goes to this node's own server if it has one (without the
/// network), else to one of the servers discovery knows, in turn. It is
/// resent until answered or its deadline passes; the server runs it once.
pub struct Client<Req, Rep, P = ()> {
    raw: RawClient,
    _types: PhantomData<Signature<Req, Rep, P>>,
}

impl<Req, Rep, P> std::fmt::Debug for Client<Req, Rep, P> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client").field("raw", &self.raw).finish()
    }
}

impl<Req, Rep, P> Clone for Client<Req, Rep, P> {
    fn clone(&self) -> Self {
        Self {
            raw: self.raw.clone(),
            _types: PhantomData,
        }
    }
}

impl<Req, Rep, P> Client<Req, Rep, P>
where
    Req: Serialize + Schema,
    Rep: DeserializeOwned + Schema,
    P: DeserializeOwned + Schema,
{
    /// The same client with another default deadline (5 s unless told).
    pub fn with_deadline(mut self, deadline: Duration) -> Self {
        self.raw = self.raw.with_deadline(deadline);
        self
    }

    /// The service's full name, with `@node` if the client targets one.
    pub fn service(&self) -> String {
        self.raw.service()
    }

    /// The nodes that serve the service now.
    pub fn servers(&self) -> Vec<String> {
        self.raw.servers()
    }

    fn encode(req: &Req) -> Result<Vec<u8>> {
        let mut message = Vec::new();
        codec::encode_native(req, &mut message)?;
        Ok(message)
    }

    /// Calls the service with the default deadline; the reply, or why not.
    pub async fn call(&self, req: &Req) -> Result<Rep> {
        self.call_within(req, self.raw.deadline).await
    }

    /// Calls the service with deadline `within` (the wait for a server
    /// included).
    pub async fn call_within(&self, req: &Req, within: Duration) -> Result<Rep> {
        self.start_within(req, within).await?.reply().await
    }

    /// Like [`Client::call`], blocking the thread.
    pub fn call_blocking(&self, req: &Req) -> Result<Rep> {
        self.call_blocking_within(req, self.raw.deadline)
    }

    /// Like [`Client::call_within`], blocking the thread.
    pub fn call_blocking_within(&self, req: &Req, within: Duration) -> Result<Rep> {
        let raw = self.raw.start_blocking(&Self::encode(req)?, within)?;
        OngoingCall::<Rep, P>::new(raw).reply_blocking()
    }

    /// Starts a call, to follow its progress ([`OngoingCall::progress`])
    /// before its reply.
    pub async fn start(&self, req: &Req) -> Result<OngoingCall<Rep, P>> {
        self.start_within(req, self.raw.deadline).await
    }

    /// Like [`Client::start`], with deadline `within`.
    pub async fn start_within(&self, req: &Req, within: Duration) -> Result<OngoingCall<Rep, P>> {
        let raw = self.raw.start(&Self::encode(req)?, within).await?;
        Ok(OngoingCall::new(raw))
    }

    /// Calls every server of the service (once discovery knows one) and
    /// gathers each one's answer by the default deadline.
    pub async fn call_all(&self, req: &Req) -> Result<Vec<Answer<Rep>>> {
        self.call_all_within(req, self.raw.deadline).await
    }

    /// Like [`Client::call_all`], with deadline `within`.
    pub async fn call_all_within(&self, req: &Req, within: Duration) -> Result<Vec<Answer<Rep>>> {
        let calls = self.raw.start_all(&Self::encode(req)?, within).await?;
        let answers = calls.into_iter().map(|(node, raw)| async move {
            let result = match raw {
                Ok(raw) => OngoingCall::<Rep, P>::new(raw).reply().await,
                Err(e) => Err(e),
            };
            Answer { node, result }
        });
        Ok(futures_util::future::join_all(answers).await)
    }
}

/// A typed call in flight: from [`Client::start`]. Dropping it before
/// its reply cancels it.
pub struct OngoingCall<Rep, P = ()> {
    raw: RawCall,
    end: Option<Result<Rep>>,
    _progress: PhantomData<fn() -> P>,
}

impl<Rep, P> std::fmt::Debug for OngoingCall<Rep, P> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OngoingCall")
            .field("raw", &self.raw)
            .finish()
    }
}

impl<Rep: DeserializeOwned + Schema, P: DeserializeOwned + Schema> OngoingCall<Rep, P> {
    fn new(raw: RawCall) -> Self {
        Self {
            raw,
            end: None,
            _progress: PhantomData,
        }
    }

    /// The server node the call went to.
    pub fn node(&self) -> &str {
        self.raw.node()
    }

    /// Takes one event: `Some(progress)`, or `None` once the call ended
    /// (its result kept for [`OngoingCall::reply`]).
    fn take(&mut self, event: Option<Event>) -> Option<Option<P>> {
        let event = match event {
            Some(event) => event,
            None => {
                self.end
                    .get_or_insert_with(|| Err(self.raw.error(Event::TimedOut)));
                return Some(None);
            }
        };
        match event {
            Event::Progress(message) => match codec::decode_native::<P>(&message) {
                Ok(p) => Some(Some(p)),
                Err(e) => {
                    let core = &self.raw.client.core;
                    core.inner.counters().drop_decode(
                        &e,
                        Some(core.channel.name()),
                        &self.raw.node,
                    );
                    None
                }
            },
            Event::Reply { message, .. } => {
                let reply =
                    codec::decode_native::<Rep>(&message).map_err(|e| Error::ServiceTypeMismatch {
                        service: self.raw.client.service(),
                        node: self.raw.node.clone(),
                        reason: format!("the reply is not a {}: {e}", Rep::SCHEMA.name),
                    });
                self.end = Some(reply);
                Some(None)
            }
            other => {
                self.end = Some(Err(self.raw.error(other)));
                Some(None)
            }
        }
    }

    /// The next progress message; `None` once the call has ended (then
    /// [`OngoingCall::reply`] gives its end at once). Progress messages
    /// that don't decode as `P` are dropped and counted as wrong type.
    pub async fn progress(&mut self) -> Option<P> {
        if self.end.is_some() {
            return None;
        }
        loop {
            let event = self.raw.next().await;
            if let Some(taken) = self.take(event) {
                return taken;
            }
        }
    }

    /// Like [`OngoingCall::progress`], blocking the thread.
    pub fn progress_blocking(&mut self) -> Option<P> {
        if self.end.is_some() {
            return None;
        }
        loop {
            let event = self.raw.next_blocking();
            if let Some(taken) = self.take(event) {
                return taken;
            }
        }
    }

    /// Waits for the reply (skipping progress not taken yet).
    pub async fn reply(mut self) -> Result<Rep> {
        while self.progress().await.is_some() {}
        self.finish()
    }

    /// Like [`OngoingCall::reply`], blocking the thread.
    pub fn reply_blocking(mut self) -> Result<Rep> {
        while self.progress_blocking().is_some() {}
        self.finish()
    }

    fn finish(&mut self) -> Result<Rep> {
        self.end
            .take()
            .unwrap_or_else(|| Err(self.raw.error(Event::TimedOut)))
    }

    /// Cancels the call (as dropping it does).
    pub fn cancel(self) {}
}

/// One node's end of a service, as discovery announces it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ServiceEnd {
    /// The node.
    pub node: String,
    /// Its session key (see [`MemberView::key`]).
    pub key: i64,
    /// The request type it announces.
    pub request: Option<TypeInfo>,
    /// The reply type.
    pub reply: Option<TypeInfo>,
    /// The progress type, if its handler (or its caller) uses progress.
    pub progress: Option<TypeInfo>,
    /// Whether a key seals the service there (servers only).
    pub sealed: bool,
}

/// A service as discovery shows it: made by [`services_of`] and
/// [`crate::Discovery::services`].
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ServiceInfo {
    /// The service's full name (`rover1/plan`).
    pub name: String,
    /// The nodes that serve it.
    pub servers: Vec<ServiceEnd>,
    /// The nodes that have a client of it.
    pub clients: Vec<ServiceEnd>,
}

impl ServiceInfo {
    /// What a server announces beside its request channel `R`, as
    /// `R@reply` (published, with the reply type). A member that publishes
    /// one serves the service whose request channel is `R`.
    pub const REPLY_SUFFIX: &'static str = crate::wire::service::REPLY;

    /// The request channel of the service whose full name is `service`:
    /// the channel its servers subscribe and callers send requests on.
    ///
    /// ```
    /// use pulicast::ServiceInfo;
    /// assert_eq!(ServiceInfo::request_channel_of("rover1/arm/plan"), "rover1/arm/.services/plan");
    /// assert_eq!(ServiceInfo::service_of("rover1/arm/.services/plan").as_deref(), Some("rover1/arm/plan"));
    /// assert_eq!(ServiceInfo::service_of("rover1/arm/pose"), None);
    /// ```
    pub fn request_channel_of(service: &str) -> String {
        crate::wire::service::request_channel_of(service)
    }

    /// The service whose request channel `channel` is; `None` for any
    /// other channel (and for what is announced beside a request channel,
    /// such as [`ServiceInfo::REPLY_SUFFIX`]).
    pub fn service_of(channel: &str) -> Option<String> {
        crate::wire::service::service_of(channel)
    }

    /// The types its servers announce (the first server's, if they differ).
    pub fn server_types(&self) -> Option<&ServiceEnd> {
        self.servers.first()
    }
}

/// The services the live `members` serve or call, by name. Pure: what
/// discovery announces, read.
///
/// ```
/// # use pulicast::{services_of, ChannelInfo, MemberView};
/// # fn f(members: Vec<MemberView>) {
/// for service in services_of(&members) {
///     let servers: Vec<&str> = service.servers.iter().map(|s| s.node.as_str()).collect();
///     println!("{}: served by {}", service.name, servers.join(", "));
/// }
/// # }
/// ```
pub fn services_of(members: &[MemberView]) -> Vec<ServiceInfo> {
    let mut by_name: std::collections::BTreeMap<String, ServiceInfo> = Default::default();
    for member in members.iter().filter(|m| m.is_live()) {
        let beside = |request: &str, suffix: &str, publishes: bool| {
            let name = format!("{request}{suffix}");
            member
                .channels
                .iter()
                .find(|c| c.name == name && if publishes { c.publishes } else { c.subscribes })
        };
        for channel in &member.channels {
            let Some(service) = wire::service_of(&channel.name) else {
                continue;
            };
            let info = by_name
                .entry(service.clone())
                .or_insert_with(|| ServiceInfo {
                    name: service,
                    servers: Vec::new(),
                    clients: Vec::new(),
                });
            // A server announces the request channel subscribed and its
            // answers published beside it; a client the other way round. A
            // node that only subscribes the request channel (a tool that
            // watches everything, a 2.x sniffer) is neither.
            for serves in [true, false] {
                let announced = match serves {
                    true => channel.subscribes,
                    false => channel.publishes,
                };
                if !announced || beside(&channel.name, wire::REPLY, serves).is_none() {
                    continue;
                }
                let ty = |suffix| {
                    beside(&channel.name, suffix, serves).and_then(|c| c.message_type.clone())
                };
                let end = ServiceEnd {
                    node: member.name.clone(),
                    key: member.key,
                    request: channel.message_type.clone(),
                    reply: ty(wire::REPLY),
                    progress: ty(wire::PROGRESS),
                    sealed: serves && beside(&channel.name, wire::SEALED, true).is_some(),
                };
                match serves {
                    true => info.servers.push(end),
                    false => info.clients.push(end),
                }
            }
        }
    }
    by_name.into_values().collect()
}

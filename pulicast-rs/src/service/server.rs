//! Servers: a service's handler, its calls run at most once each, and
//! the builder that sets its options.

use std::future::Future;
use std::marker::PhantomData;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Instant;

use bytes::Bytes;
use serde::de::DeserializeOwned;
use serde::Serialize;

use super::fault::Fault;
use super::is_unit;
use super::service_names;
use super::type_info;
use super::Held;
use crate::channel::{Channel, Namespace};
use crate::error::{Error, Result};
use crate::proto::service::{ServiceCounts, ServiceLimits};
use crate::runtime::services::{LocalServer, ReplyTo};
use crate::runtime::serving::{Runner, Running, ServerCore, Targets};
use crate::runtime::Inner;
use crate::subscription::{CallbackSubscription, Message};
use crate::wire::service::{self as wire, code};
use crate::wire::{self as codec};
use crate::{Schema, TypeInfo};

/// What a handler knows of its call, and how it sends progress: given to
/// the handlers of [`ServerBuilder::serve_with`] and
/// [`ServerBuilder::serve_blocking_with`]. `P` is the progress type.
///
/// # Example
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::{CallContext, Fault};
/// let _drive = node.server("drive").serve_blocking_with(
///     |metres: u32, call: CallContext<u32>| -> Result<String, Fault> {
///         for done in 0..metres {
///             if call.is_cancelled() { return Err(Fault::msg("stopped")); }
///             call.progress(&done)?;                    // pulicast::Error -> Fault via From
///             std::thread::sleep(std::time::Duration::from_millis(100));
///         }
///         Ok(format!("drove {metres} m for {:?}", call.caller()))
///     },
/// )?;
/// # Ok(()) }
/// ```
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
            .field("call", &self.running.call())
            .field("caller", &self.caller())
            .finish()
    }
}

impl<P> CallContext<P> {
    fn new(running: Arc<Running>) -> Self {
        CallContext {
            running,
            _progress: PhantomData,
        }
    }

    /// Whether the caller cancelled the call, or its deadline passed. An
    /// async handler is dropped then; a blocking one should look here
    /// between steps and return.
    pub fn is_cancelled(&self) -> bool {
        self.running.is_cancelled()
    }

    /// Where the caller is; `None` for a call from this node.
    pub fn caller(&self) -> Option<SocketAddr> {
        self.running.caller()
    }

    /// When the caller stops waiting, as it said in its request.
    pub fn deadline(&self) -> Option<Instant> {
        self.running.deadline()
    }

    /// The node the caller named as the server (empty: any server). A
    /// server of [`ServerBuilder::serve_for`] answers for several.
    pub fn target(&self) -> &str {
        self.running.target()
    }

    /// Sends a progress message already encoded (fingerprint first), as a
    /// bridge passes on another server's progress; otherwise as
    /// [`CallContext::progress`].
    pub fn progress_encoded(&self, message: &[u8]) -> Result<()> {
        self.running.progress(message)
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
        let mut message = Vec::new();
        codec::encode_native(value, &mut message)?;
        self.running.progress(&message)
    }
}

/// The message types a server announces, for
/// [`ServerBuilder::serve_raw`]: each `None` for raw bytes (and, for
/// progress, for none sent).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ServiceTypes {
    /// The request type.
    pub request: Option<TypeInfo>,
    /// The reply type.
    pub reply: Option<TypeInfo>,
    /// The progress type, if the handler sends progress.
    pub progress: Option<TypeInfo>,
}

/// A service this node serves: made by [`Namespace::serve`] and the
/// other `serve` methods; dropping it stops serving (calls running end
/// as they end, their answers still sent).
///
/// # Example
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::Fault;
/// let server = node.serve("double", |x: i64| async move {
///     x.checked_mul(2).ok_or(Fault::msg("too large")) // caller gets Error::CallFailed
/// })?;                                                 // keep it: dropping it stops serving
/// tokio::time::sleep(std::time::Duration::from_secs(60)).await;
/// let c = server.counts();
/// println!("{}: {} run, {} busy, {} running", server.service(), c.run, c.busy, server.running());
/// # Ok(()) }
/// ```
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
    pub fn counts(&self) -> ServiceCounts {
        self.core.counts()
    }

    /// Calls running now.
    pub fn running(&self) -> usize {
        self.core.running()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.core.stop();
    }
}

/// A server being made, with options: made by [`Namespace::server`].
///
/// # Example
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use std::time::Duration;
/// use pulicast::{Fault, ServiceLimits};
/// let _plan = node
///     .server("plan")
///     .limits(ServiceLimits { longest: Duration::from_secs(30), ..ServiceLimits::default() })
///     .concurrency(2)                                   // after `limits`, which sets it too
///     .serve_blocking(|goal: (f64, f64)| -> Result<u32, Fault> {
///         Ok((goal.0.abs() + goal.1.abs()) as u32)      // runs on a blocking thread
///     })?;
/// # Ok(()) }
/// ```
#[must_use = "a server serves once one of its serve methods is called"]
#[derive(Debug)]
pub struct ServerBuilder {
    pub(super) ns: Namespace,
    pub(super) name: String,
    pub(super) limits: ServiceLimits,
}

impl ServerBuilder {
    /// Calls run at once (16 by default); more are answered busy.
    pub fn concurrency(mut self, calls: usize) -> Self {
        self.limits.concurrency = calls;
        self
    }

    /// All the server's bounds (see [`ServiceLimits`]).
    pub fn limits(mut self, limits: ServiceLimits) -> Self {
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
        let run: Runner = Box::new(move |bytes, running| {
            let handler = Arc::clone(&handler);
            Box::pin(async move {
                let ran = async {
                    let req = decode_request::<Req>(&bytes)?;
                    let reply = handler(req, CallContext::new(running)).await?;
                    encode_reply(&reply)
                };
                ran.await.map_err(Fault::into_failure)
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
        let core = ServerCore::new(&inner, channel, limits, blocking, run, answers_for);
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
        let run = raw_runner(handler);
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
        let run = blocking_runner(move |bytes: Bytes, call: CallContext<()>| {
            let req = decode_request::<Req>(&bytes)?;
            let reply = handler(req, CallContext::new(call.running))?;
            encode_reply(&reply)
        });
        self.start::<Req, Rep, P>(run, true)
    }

    /// Serves with message types known only at run time, as a language
    /// binding or a gateway knows them: `types` is what discovery
    /// announces (so typed clients and `puli call` encode for it), and
    /// `handler` gets each request as it came (fingerprint first) and
    /// returns the reply encoded in `types.reply`, or a [`Fault`]. Progress
    /// goes with [`CallContext::progress_encoded`]. The handler is async,
    /// run on the node's runtime, as [`ServerBuilder::serve`]'s.
    ///
    /// ```
    /// use pulicast::{type_info_of, Fault, ServiceTypes};
    /// # let port = pulicast::unused_port()?;
    /// let node = pulicast::Node::new("doubler")
    ///     .interface(std::net::Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start_blocking()?;
    /// let types = ServiceTypes {
    ///     request: Some(type_info_of::<i64>()),
    ///     reply: Some(type_info_of::<i64>()),
    ///     progress: None,
    /// };
    /// // Read and written here with the 2.x primitives' own codec.
    /// let _server = node.server("double").serve_raw(types, |request, _call| async move {
    ///     let pulicast::Primitive::I64(x) = pulicast::Primitive::decode(&request)
    ///         .map_err(|e| Fault::new(1, e.to_string()))?
    ///     else {
    ///         return Err(Fault::new(1, "not an int64_msg"));
    ///     };
    ///     let mut reply = Vec::new();
    ///     pulicast::Primitive::I64(2 * x).encode(&mut reply);
    ///     Ok(reply)
    /// })?;
    /// let doubled = node.client::<i64, i64>("double")?.call_blocking(&21)?;
    /// assert_eq!(doubled, 42);
    /// # Ok::<(), pulicast::Error>(())
    /// ```
    pub fn serve_raw<F, Fut>(self, types: ServiceTypes, handler: F) -> Result<Server>
    where
        F: Fn(Bytes, CallContext<()>) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Vec<u8>, Fault>> + Send + 'static,
    {
        let run = raw_runner(handler);
        self.start_with(run, false, types)
    }

    /// Like [`ServerBuilder::serve_raw`], with a blocking handler run on
    /// the runtime's blocking threads (one that holds a lock of its own, as
    /// an interpreter's, for as long as it runs).
    pub fn serve_raw_blocking<F>(self, types: ServiceTypes, handler: F) -> Result<Server>
    where
        F: Fn(Bytes, CallContext<()>) -> Result<Vec<u8>, Fault> + Send + Sync + 'static,
    {
        self.start_with(blocking_runner(handler), true, types)
    }

    fn start<Req: Schema, Rep: Schema, P: Schema>(
        self,
        run: Runner,
        blocking: bool,
    ) -> Result<Server> {
        let types = ServiceTypes {
            request: type_info::<Req>(),
            reply: type_info::<Rep>(),
            progress: (!is_unit::<P>()).then(type_info::<P>).flatten(),
        };
        let progress = !is_unit::<P>();
        self.start_announcing(run, blocking, types, progress)
    }

    fn start_with(self, run: Runner, blocking: bool, types: ServiceTypes) -> Result<Server> {
        let progress = types.progress.is_some();
        self.start_announcing(run, blocking, types, progress)
    }

    /// Starts serving, announcing `types` (and a progress channel if
    /// `progress`).
    fn start_announcing(
        self,
        run: Runner,
        blocking: bool,
        types: ServiceTypes,
        progress: bool,
    ) -> Result<Server> {
        let (service, requests, inner, core) = self.core(run, blocking, None)?;
        let channel = Arc::clone(core.channel());
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
        held.hold(&inner, Arc::clone(&channel), false, types.request);
        let reply = inner.channel_state(&format!("{request}{}", wire::REPLY));
        held.hold(&inner, reply, true, types.reply);
        if progress {
            let channel = inner.channel_state(&format!("{request}{}", wire::PROGRESS));
            held.hold(&inner, channel, true, types.progress);
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

/// The runner of a handler of raw messages, run on the node's runtime.
fn raw_runner<F, Fut>(handler: F) -> Runner
where
    F: Fn(Bytes, CallContext<()>) -> Fut + Send + Sync + 'static,
    Fut: Future<Output = Result<Vec<u8>, Fault>> + Send + 'static,
{
    Box::new(move |bytes, running| {
        let ran = handler(bytes, CallContext::new(running));
        Box::pin(async move { ran.await.map_err(Fault::into_failure) })
    })
}

/// The runner of a blocking handler of raw messages, run on the
/// runtime's blocking threads; a panic is the call's failure.
fn blocking_runner<F>(handler: F) -> Runner
where
    F: Fn(Bytes, CallContext<()>) -> Result<Vec<u8>, Fault> + Send + Sync + 'static,
{
    let handler = Arc::new(handler);
    Box::new(move |bytes, running| {
        let handler = Arc::clone(&handler);
        Box::pin(async move {
            let ran =
                tokio::task::spawn_blocking(move || handler(bytes, CallContext::new(running)))
                    .await;
            ran.unwrap_or_else(|_| Err(Fault::new(code::PANICKED, "the handler panicked")))
                .map_err(Fault::into_failure)
        })
    })
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

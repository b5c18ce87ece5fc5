//! Typed clients and calls, on top of the raw ones.

use std::marker::PhantomData;
use std::time::Duration;

use serde::de::DeserializeOwned;
use serde::Serialize;

use super::call::RawCall;
use super::client::Answer;
use super::client::RawClient;
use crate::error::{Error, Result};
use crate::proto::call::Event;
use crate::wire::{self as codec};
use crate::Schema;

/// What a typed client takes and gives, as a type.
pub(super) type Signature<Req, Rep, P> = fn(&Req) -> (Rep, P);

/// A typed client of a service: made by [`Namespace::client`](crate::Namespace::client) (or
/// [`Namespace::client_with_progress`](crate::Namespace::client_with_progress) for progress of type `P`).
///
/// A call goes to this node's own server if it has one (without the
/// network), else to one of the servers discovery knows, in turn. It is
/// resent until answered or its deadline passes; the server runs it once.
///
/// # Example
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use std::time::Duration;
/// let double = node.client::<i64, i64>("double")?;        // request i64, reply i64
/// let four = double.call(&2).await?;                       // deadline: DEFAULT_DEADLINE (5 s)
/// let quick = double.call_within(&2, Duration::from_millis(200)).await;
/// let only_a = node.client::<i64, i64>("double@planner_a")?; // that node's server only
/// for answer in double.call_all(&2).await? {               // one answer per server
///     println!("{}: {:?}", answer.node, answer.result);
/// }
/// # let _ = (four, quick, only_a); Ok(()) }
/// ```
pub struct Client<Req, Rep, P = ()> {
    pub(super) raw: RawClient,
    pub(super) _types: PhantomData<Signature<Req, Rep, P>>,
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

    /// The same client, calling the nearest server in DROS's order: this
    /// node's configuration before none, each from the client's namespace
    /// out to the root, passing over a server that is busy, gone, of
    /// other types or silent (see [`RawClient::nearest`]).
    ///
    /// ```no_run
    /// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
    /// // A node in configuration `alice` and namespace `rover1`: alice's
    /// // rover1/laser, alice's laser, everyone's rover1/laser, everyone's laser.
    /// let laser = node.client::<String, f32>("laser")?.nearest()?;
    /// let range = laser.call(&"front".to_string()).await?; // the first that answers
    /// # let _ = range; Ok(()) }
    /// ```
    pub fn nearest(mut self) -> Result<Self> {
        self.raw = self.raw.nearest()?;
        Ok(self)
    }

    /// The service's full name, with `@node` if the client targets one.
    pub fn service(&self) -> String {
        self.raw.service()
    }

    /// The nodes that serve the service now; for a client of the nearest
    /// server, `service@node` in the order calls try them (see
    /// [`RawClient::servers`]).
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
///
/// # Example
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// let drive = node.client_with_progress::<u32, String, u32>("drive")?;
/// let mut call = drive.start(&5).await?;                // dropping `call` cancels it
/// let server = call.node().to_string();
/// while let Some(done) = call.progress().await {
///     println!("{server}: {done} of 5 m");
/// }
/// println!("{}", call.reply().await?);
/// # Ok(()) }
/// ```
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
    pub(super) fn new(raw: RawCall) -> Self {
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
                    let core = &self.raw.client().core;
                    core.inner.counters().drop_decode(
                        &e,
                        Some(core.channel.name()),
                        self.raw.node(),
                    );
                    None
                }
            },
            Event::Reply { message, .. } => {
                let reply =
                    codec::decode_native::<Rep>(&message).map_err(|e| Error::ServiceTypeMismatch {
                        service: self.raw.client().service(),
                        node: self.raw.node().to_owned(),
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

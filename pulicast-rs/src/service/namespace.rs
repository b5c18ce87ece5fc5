//! The service methods of [`Namespace`]: serving and making clients.

use std::future::Future;
use std::marker::PhantomData;

use serde::de::DeserializeOwned;
use serde::Serialize;

use super::client::RawClient;
use super::client::Types;
use super::fault::Fault;
use super::is_unit;
use super::server::Server;
use super::server::ServerBuilder;
use super::type_info;
use super::typed::Client;
use crate::channel::Namespace;
use crate::error::Result;
use crate::proto::service::ServiceLimits;
use crate::Schema;

impl Namespace {
    /// Starts making a server of service `name` in this namespace, to set
    /// its options (see [`ServerBuilder`]).
    pub fn server(&self, name: &str) -> ServerBuilder {
        ServerBuilder {
            ns: self.clone(),
            name: name.to_string(),
            limits: ServiceLimits::default(),
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
    /// progress messages of type `P` ([`OngoingCall::progress`](crate::OngoingCall::progress)).
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

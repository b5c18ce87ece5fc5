//! `Namespace` and `Channel`.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use pulicast::{TypeEncoding, TypeInfo};
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};

use crate::convert::{encode_as, outgoing, Outgoing};
use crate::setting::Setting;
use crate::subscription::{CallbackSubscription, Subscription};
use crate::to_py;

/// A place in the channel hierarchy (`rover1/left_arm`): made by
/// `Node.ns` and `Namespace.ns`. A `Node` is one too: its own namespace.
#[pyclass(module = "pulicast_rs", frozen, subclass)]
pub(crate) struct Namespace {
    ns: pulicast::Namespace,
    /// Kept so the node runs while its namespaces and channels are used.
    node: pulicast::Node,
}

impl Namespace {
    pub(crate) fn new(ns: pulicast::Namespace, node: &pulicast::Node) -> Self {
        Self {
            ns,
            node: node.clone(),
        }
    }
}

#[pymethods]
impl Namespace {
    /// The resolved path (`""` for the root).
    #[getter]
    fn path(&self) -> String {
        self.ns.path().to_string()
    }

    /// The channel `name` in this namespace. Raises `ValueError` for a bad
    /// name (or a namespace whose own name was bad).
    fn channel(&self, name: &str) -> PyResult<Channel> {
        let channel = self.ns.try_channel(name).map_err(to_py)?;
        Ok(Channel::new(channel, &self.node))
    }

    /// A namespace below this one (`..` goes up; a leading `/` starts at
    /// the root).
    fn ns(&self, path: &str) -> Namespace {
        Namespace::new(self.ns.ns(path), &self.node)
    }

    /// A distributed setting `name` in this namespace, owned by this node:
    /// `setting("max_speed", 1.5, range=(0, 2), unit="m/s")`. Its type is
    /// the initial value's (`bool`, `int`, `float` or `str`). Checks:
    /// `range=(lo, hi)`, `at_least`, `at_most`, `one_of=[...]`,
    /// `read_only`, and `check=f`, where `f(value)` returns `None`/`True`
    /// to accept, or the reason it refuses. `ValueError` if the initial
    /// value fails them or the name is bad; `TypeError` for a value of
    /// another type.
    #[pyo3(signature = (name, initial, *, range = None, at_least = None, at_most = None, one_of = None, read_only = false, check = None, unit = "", description = ""))]
    #[allow(clippy::too_many_arguments)]
    fn setting(
        &self,
        name: &str,
        initial: &Bound<'_, PyAny>,
        range: Option<Bound<'_, PyAny>>,
        at_least: Option<Bound<'_, PyAny>>,
        at_most: Option<Bound<'_, PyAny>>,
        one_of: Option<Bound<'_, PyAny>>,
        read_only: bool,
        check: Option<Py<PyAny>>,
        unit: &str,
        description: &str,
    ) -> PyResult<Setting> {
        Setting::new(
            &self.ns,
            &self.node,
            name,
            initial,
            range,
            at_least,
            at_most,
            one_of,
            read_only,
            check,
            unit,
            description,
        )
    }

    /// Serves `handler` as service `name`: `handler(request)` or
    /// `handler(request, call)` returns the reply; an exception is the
    /// caller's failure (its type and message). The types are the
    /// handler's annotations (`def double(x: int) -> int`), or `request=`,
    /// `reply=` (`bool`, `int`, `float`, `str`, `bytes`), and `progress=`
    /// for `call.progress(value)`. Handlers run on the node's blocking
    /// threads, up to `concurrency` (16) at once. Without `handler`, a
    /// decorator: `@node.serve("double")`. Keep the `Server`: serving
    /// stops when it is dropped.
    #[pyo3(signature = (name, handler = None, *, request = None, reply = None, progress = None, concurrency = None))]
    #[allow(clippy::too_many_arguments)]
    fn serve(
        &self,
        py: Python<'_>,
        name: &str,
        handler: Option<Bound<'_, PyAny>>,
        request: Option<Bound<'_, PyAny>>,
        reply: Option<Bound<'_, PyAny>>,
        progress: Option<Bound<'_, PyAny>>,
        concurrency: Option<usize>,
    ) -> PyResult<Py<PyAny>> {
        crate::service::serve_or_decorate(
            py,
            &self.ns,
            &self.node,
            name,
            handler,
            request,
            reply,
            progress,
            concurrency,
        )
    }

    /// A client of service `name` (`"double"`, `"double@node"` for that
    /// node's server only); `timeout` is its calls' default, in seconds.
    #[pyo3(signature = (name, *, timeout = 5.0))]
    fn client(&self, name: &str, timeout: f64) -> PyResult<crate::service::Client> {
        crate::service::Client::new(&self.ns, &self.node, name, timeout)
    }

    fn __repr__(&self) -> String {
        format!("Namespace({:?})", self.ns.path())
    }
}

/// How long a native type found for dicts is used before discovery is
/// asked again.
const LOOK_AGAIN: Duration = Duration::from_millis(100);

/// One channel, by its resolved name.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct Channel {
    channel: pulicast::Channel,
    node: pulicast::Node,
    /// The native type dicts are published as, and when it was last
    /// looked for: again after [`LOOK_AGAIN`], so a member that announces
    /// another type (a new version) is followed.
    native: Mutex<Option<(TypeInfo, Instant)>>,
}

impl Channel {
    /// The native type a live member (not this one, which declares what it
    /// found) announces on the channel: publishers' first, then
    /// subscribers'.
    fn announced_native(&self) -> Option<TypeInfo> {
        let name = self.channel.name();
        let members = self.node.discovery().live_members();
        let mut found: Vec<(bool, TypeInfo)> = members
            .into_iter()
            .flat_map(|m| m.channels)
            .filter(|c| c.name == name)
            .filter_map(|c| {
                let ty = c.message_type?;
                (ty.encoding == TypeEncoding::Native).then_some((!c.publishes, ty))
            })
            .collect();
        found.sort_by_key(|(not_published, _)| *not_published);
        found.into_iter().next().map(|(_, ty)| ty)
    }

    fn publish_native(&self, py: Python<'_>, value: &Bound<'_, PyAny>) -> PyResult<()> {
        let known = crate::lock(&self.native).clone();
        let ty = match known {
            Some((ty, looked)) if looked.elapsed() < LOOK_AGAIN => ty,
            Some((ty, _)) => {
                // Kept if nobody else announces one now.
                let found = py.detach(|| self.announced_native()).unwrap_or(ty);
                *crate::lock(&self.native) = Some((found.clone(), Instant::now()));
                found
            }
            None => {
                let found = py.detach(|| self.announced_native()).ok_or_else(|| {
                    PyTypeError::new_err(format!(
                        "no member announces a native type on {}: a dict or list is \
                         published as the type a Rust publisher or subscriber of the \
                         channel announces",
                        self.channel.name()
                    ))
                })?;
                *crate::lock(&self.native) = Some((found.clone(), Instant::now()));
                found
            }
        };
        let payload = encode_as(value, Some(&ty))?;
        py.detach(|| {
            self.channel.declare_type(ty)?;
            self.channel.publish_bytes(&payload)
        })
        .map_err(to_py)
    }
}

impl Channel {
    pub(crate) fn new(channel: pulicast::Channel, node: &pulicast::Node) -> Self {
        Self {
            channel,
            node: node.clone(),
            native: Mutex::new(None),
        }
    }
}

#[pymethods]
impl Channel {
    /// The resolved name (`rover1/pose`).
    #[getter]
    fn name(&self) -> String {
        self.channel.name().to_string()
    }

    /// Publishes `value`: `bool`, `int` (as a 2.x `int64_msg`), `float`
    /// (`double_msg`), `str` (`string_msg`), or `bytes`/`bytearray` as
    /// they are; a dict or list as the native (Rust) type another member
    /// announces on the channel (`ValueError` naming the field that does
    /// not fit it). Raises `TypeError` for other types or a channel whose
    /// type nobody announces, `OverflowError` for an `int` beyond 64 bits,
    /// `PulicastError` once the node stopped.
    fn publish(&self, py: Python<'_>, value: &Bound<'_, PyAny>) -> PyResult<()> {
        if value.is_instance_of::<PyDict>()
            || value.is_instance_of::<PyList>()
            || value.is_instance_of::<PyTuple>()
        {
            return self.publish_native(py, value);
        }
        let message = outgoing(value)?;
        let channel = &self.channel;
        py.detach(|| match &message {
            Outgoing::Bool(b) => channel.publish(b),
            Outgoing::Int(i) => channel.publish(i),
            Outgoing::Float(f) => channel.publish(f),
            Outgoing::Str(s) => channel.publish(s.as_str()),
            Outgoing::Raw(bytes) => channel.publish_bytes(bytes),
        })
        .map_err(to_py)
    }

    /// Publishes `payload` as it is (no type): what `publish` does with
    /// `bytes`, for any bytes-like object.
    fn publish_bytes(&self, py: Python<'_>, payload: &Bound<'_, PyAny>) -> PyResult<()> {
        let payload = crate::convert::bytes_of(payload)?;
        py.detach(|| self.channel.publish_bytes(&payload))
            .map_err(to_py)
    }

    /// Subscribes. Without `callback`: a `Subscription` to receive from
    /// (`recv(timeout)`, or iterate it). With one: `callback(message)` is
    /// called on a thread of the subscription for each message, and a
    /// `CallbackSubscription` returned; keep it while the callback should
    /// run.
    #[pyo3(signature = (callback = None))]
    fn subscribe(&self, py: Python<'_>, callback: Option<Py<PyAny>>) -> PyResult<Py<PyAny>> {
        match callback {
            None => {
                let subscription = Subscription::new(py, &self.channel, &self.node)?;
                Ok(Py::new(py, subscription)?.into_any())
            }
            Some(callback) => {
                let subscription =
                    CallbackSubscription::new(py, &self.channel, &self.node, callback)?;
                Ok(Py::new(py, subscription)?.into_any())
            }
        }
    }

    /// The names of the nodes that publish the channel now, as discovery
    /// knows them (this node included).
    fn publishers(&self, py: Python<'_>) -> Vec<String> {
        names(py.detach(|| self.channel.publishers()))
    }

    /// The names of the nodes that subscribe the channel now, as
    /// discovery knows them (this node included).
    fn subscribers(&self, py: Python<'_>) -> Vec<String> {
        names(py.detach(|| self.channel.subscribers()))
    }

    /// Waits up to `timeout` seconds until some node publishes the channel,
    /// and returns its name; `PulicastError` if none does in time. Ctrl-C
    /// interrupts the wait.
    fn wait_for_publisher(&self, py: Python<'_>, timeout: f64) -> PyResult<String> {
        let timeout = crate::bounded_seconds(timeout)?;
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let slice = left.min(crate::SIGNAL_CHECK);
            match py.detach(|| self.channel.wait_for_publisher_blocking(slice)) {
                Ok(member) => return Ok(member.name),
                Err(pulicast::Error::Timeout(_)) if slice < left => {}
                // The time asked for, not the last slice's.
                Err(pulicast::Error::Timeout(_)) => {
                    return Err(to_py(pulicast::Error::Timeout(timeout)))
                }
                Err(e) => return Err(to_py(e)),
            }
            py.check_signals()?;
        }
    }

    /// Packs this channel's messages into shared datagrams, each sent when
    /// full or at most `max_delay` seconds after its first message (at
    /// most 1 s): many small messages a second at a fraction of the
    /// cost, for up to `max_delay` of latency. Subscribers need nothing
    /// special. While a 2.x node subscribes the channel, its messages go
    /// out singly (2.x can't read batches).
    fn enable_batching(&self, py: Python<'_>, max_delay: f64) -> PyResult<()> {
        let max_delay = crate::subscription::seconds(max_delay)?;
        py.detach(|| self.channel.enable_batching(max_delay))
            .map_err(to_py)
    }

    /// Sends what is pending and publishes one message per datagram again.
    fn disable_batching(&self, py: Python<'_>) -> PyResult<()> {
        py.detach(|| self.channel.disable_batching()).map_err(to_py)
    }

    /// Sends the pending batch now (if batching is on and messages wait).
    fn flush(&self, py: Python<'_>) -> PyResult<()> {
        py.detach(|| self.channel.flush()).map_err(to_py)
    }

    fn __repr__(&self) -> String {
        format!("Channel({:?})", self.channel.name())
    }
}

/// The names of `members`.
fn names(members: Vec<pulicast::MemberView>) -> Vec<String> {
    members.into_iter().map(|m| m.name).collect()
}

//! Services: serving a Python function (`Server`, `Call`) and calling
//! servers of any language (`Client`, `OngoingCall`).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use pulicast::{
    type_info_of, Bytes, CallEvent, Fault, RawCall, RawClient, ServiceEnd, ServiceTypes,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyBytes, PyDict, PyFloat, PyInt, PyString};

use crate::convert::{encode_as, read, Known};
use crate::{to_py, PulicastError};

/// The message type a Python type stands for in a service: the 2.x
/// primitives' for `bool`, `int` (`int64_msg`), `float` (`double_msg`) and
/// `str`; raw bytes (`None`) for `bytes`.
fn type_of(what: &str, ty: &Bound<'_, PyAny>) -> PyResult<Option<pulicast::TypeInfo>> {
    let py = ty.py();
    let is = |t: &Bound<'_, PyAny>| ty.is(t);
    if is(py.get_type::<PyBool>().as_any()) {
        Ok(Some(type_info_of::<bool>()))
    } else if is(py.get_type::<PyInt>().as_any()) {
        Ok(Some(type_info_of::<i64>()))
    } else if is(py.get_type::<PyFloat>().as_any()) {
        Ok(Some(type_info_of::<f64>()))
    } else if is(py.get_type::<PyString>().as_any()) {
        Ok(Some(type_info_of::<String>()))
    } else if is(py.get_type::<PyBytes>().as_any()) {
        Ok(None)
    } else {
        Err(PyTypeError::new_err(format!(
            "a Python server's {what} is bool, int, float, str or bytes, not {}",
            ty.repr()?
        )))
    }
}

/// What `func` is served with: its types (given, else its annotations)
/// and whether it takes the call as a second argument.
struct Served {
    types: ServiceTypes,
    with_call: bool,
}

fn served(
    func: &Bound<'_, PyAny>,
    request: Option<&Bound<'_, PyAny>>,
    reply: Option<&Bound<'_, PyAny>>,
    progress: Option<&Bound<'_, PyAny>>,
) -> PyResult<Served> {
    let py = func.py();
    if !func.is_callable() {
        return Err(PyTypeError::new_err(
            "a server's handler must be callable: it is called with each request",
        ));
    }
    let inspect = py.import("inspect")?;
    let parameters: Vec<String> = inspect
        .call_method1("signature", (func,))?
        .getattr("parameters")?
        .call_method0("keys")?
        .try_iter()?
        .map(|k| k?.extract::<String>())
        .collect::<PyResult<_>>()?;
    let with_call = match parameters.len() {
        1 => false,
        2 => true,
        n => {
            return Err(PyTypeError::new_err(format!(
                "a server's handler takes (request) or (request, call), not {n} arguments"
            )))
        }
    };
    // Annotations as `typing` resolves them (strings included); none if
    // it can't.
    let hints = py
        .import("typing")?
        .call_method1("get_type_hints", (func,))
        .ok()
        .and_then(|h| h.cast_into::<PyDict>().ok());
    let hint = |name: &str| -> PyResult<Option<Bound<'_, PyAny>>> {
        match &hints {
            Some(h) => h.get_item(name),
            None => Ok(None),
        }
    };
    let pick = |what: &str,
                given: Option<&Bound<'_, PyAny>>,
                annotated: Option<Bound<'_, PyAny>>|
     -> PyResult<Option<pulicast::TypeInfo>> {
        match given.cloned().or(annotated) {
            Some(ty) => type_of(what, &ty),
            None => Err(PyTypeError::new_err(format!(
                "the server's {what} type is not known: annotate the handler \
                 (def double(x: int) -> int) or give {what}="
            ))),
        }
    };
    let request = pick("request", request, hint(&parameters[0])?)?;
    let reply = pick("reply", reply, hint("return")?)?;
    let progress = match progress {
        Some(ty) => match type_of("progress", ty)? {
            Some(info) => Some(info),
            // A raw progress type would read as none declared.
            None => {
                return Err(PyTypeError::new_err(
                    "a Python server's progress is bool, int, float or str",
                ))
            }
        },
        None => None,
    };
    Ok(Served {
        types: ServiceTypes {
            request,
            reply,
            progress,
        },
        with_call,
    })
}

/// A service this node serves: made by `Node.serve` (or its decorator).
/// Serving stops when it is closed, or dropped.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct Server {
    server: Mutex<Option<pulicast::Server>>,
    service: String,
    /// Kept so the node runs while the server is held.
    _node: pulicast::Node,
}

#[pymethods]
impl Server {
    /// The service's full name (`rover1/double`).
    #[getter]
    fn service(&self) -> String {
        self.service.clone()
    }

    /// Calls running now.
    #[getter]
    fn running(&self) -> usize {
        crate::lock(&self.server)
            .as_ref()
            .map_or(0, pulicast::Server::running)
    }

    /// Stops serving (calls running finish, their answers sent).
    fn close(&self, py: Python<'_>) {
        py.detach(|| drop(crate::lock(&self.server).take()));
    }

    fn __enter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    #[pyo3(signature = (*_args))]
    fn __exit__(&self, py: Python<'_>, _args: &Bound<'_, pyo3::types::PyTuple>) {
        self.close(py);
    }

    fn __repr__(&self) -> String {
        format!("Server({:?})", self.service)
    }
}

/// A call a handler runs: `progress(value)` before the reply, `cancelled`
/// to stop early.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct Call {
    context: pulicast::CallContext<()>,
    progress: Option<pulicast::TypeInfo>,
    sends_progress: bool,
}

#[pymethods]
impl Call {
    /// Whether the caller cancelled the call, or its deadline passed: a
    /// handler should look here between steps and return.
    #[getter]
    fn cancelled(&self) -> bool {
        self.context.is_cancelled()
    }

    /// Where the caller is (`"ip:port"`); `None` for a call from this node.
    #[getter]
    fn caller(&self) -> Option<String> {
        self.context.caller().map(|a| a.to_string())
    }

    /// Seconds left before the caller stops waiting, if it said.
    #[getter]
    fn time_left(&self) -> Option<f64> {
        self.context
            .deadline()
            .map(|d| d.saturating_duration_since(Instant::now()).as_secs_f64())
    }

    /// Sends a progress message to the caller, of the server's `progress`
    /// type. Lost ones are not sent again; after a cancel, nothing is sent.
    fn progress(&self, py: Python<'_>, value: &Bound<'_, PyAny>) -> PyResult<()> {
        if !self.sends_progress {
            return Err(PyValueError::new_err(
                "this server declared no progress type: serve(..., progress=int)",
            ));
        }
        if self.context.is_cancelled() {
            return Ok(());
        }
        let message = encode_as(value, self.progress.as_ref())?;
        py.detach(|| self.context.progress_encoded(&message))
            .map_err(to_py)
    }
}

/// The reply message of `func`'s answer to a request, or the fault the
/// caller sees.
fn answer(
    func: &Py<PyAny>,
    served: &Served,
    request: &[u8],
    context: pulicast::CallContext<()>,
) -> Result<Vec<u8>, Fault> {
    let mut answered = Err(Fault::msg("the program is exiting"));
    crate::with_python(|py| {
        let ran = || -> PyResult<Result<Vec<u8>, Fault>> {
            let value = match &served.types.request {
                None => PyBytes::new(py, request).into_any(),
                // Of the type announced only: a caller that encoded
                // another is refused, its handler never run.
                Some(ty) if request.get(..8) == Some(&ty.fingerprint[..]) => {
                    match read(py, request, Some(&Known::new(ty.clone()))) {
                        // Read as the type, not shown as bytes for not fitting it.
                        Ok((name, v)) if name == ty.name => v,
                        _ => {
                            return Ok(Err(Fault::new(
                                Fault::BAD_REQUEST,
                                format!("the request is not a {}", ty.name),
                            )))
                        }
                    }
                }
                Some(ty) => {
                    return Ok(Err(Fault::new(
                        Fault::BAD_REQUEST,
                        format!("the request is not a {}", ty.name),
                    )))
                }
            };
            let reply = if served.with_call {
                let call = Call {
                    context,
                    progress: served.types.progress.clone(),
                    sends_progress: served.types.progress.is_some(),
                };
                func.call1(py, (value, call))?
            } else {
                func.call1(py, (value,))?
            };
            // An `async def` handler: its coroutine runs to its end here,
            // on an event loop of this call (the handler's thread has none).
            let coroutine = py
                .import("inspect")?
                .call_method1("iscoroutine", (&reply,))?
                .is_truthy()?;
            let reply = if coroutine {
                py.import("asyncio")?
                    .call_method1("run", (reply,))?
                    .unbind()
            } else {
                reply
            };
            Ok(Ok(encode_as(reply.bind(py), served.types.reply.as_ref())?))
        };
        answered = match ran() {
            Ok(answer) => answer,
            // The exception is the caller's failure: its type and words.
            Err(e) => {
                let kind = e
                    .get_type(py)
                    .name()
                    .map_or_else(|_| "Exception".to_string(), |n| n.to_string());
                Err(Fault::msg(format!("{kind}: {}", e.value(py))))
            }
        };
    });
    answered
}

/// Serves `func` as service `name` in namespace `ns`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn serve(
    ns: &pulicast::Namespace,
    node: &pulicast::Node,
    name: &str,
    func: &Bound<'_, PyAny>,
    request: Option<&Bound<'_, PyAny>>,
    reply: Option<&Bound<'_, PyAny>>,
    progress: Option<&Bound<'_, PyAny>>,
    concurrency: Option<usize>,
) -> PyResult<Server> {
    let py = func.py();
    let served = Arc::new(served(func, request, reply, progress)?);
    let types = served.types.clone();
    let func: Py<PyAny> = func.clone().unbind();
    let mut builder = ns.server(name);
    if let Some(calls) = concurrency {
        builder = builder.concurrency(calls);
    }
    let server = py
        .detach(|| {
            builder.serve_raw_blocking(types, move |request: Bytes, call| {
                answer(&func, &served, &request, call)
            })
        })
        .map_err(to_py)?;
    Ok(Server {
        service: server.service().to_string(),
        server: Mutex::new(Some(server)),
        _node: node.clone(),
    })
}

/// The types the server a call goes to announces, once discovery knows
/// it (this node's own server included).
fn announced(node: &pulicast::Node, client: &RawClient) -> Option<ServiceEnd> {
    let full = client.service();
    let base = full.split_once('@').map_or(full.as_str(), |(s, _)| s);
    let first = client.servers().into_iter().next()?;
    let (service, server) = match first.split_once('@') {
        Some((s, n)) => (s.to_string(), n.to_string()),
        None => (base.to_string(), first),
    };
    // Live members only: a server gone within the last seconds may have
    // started again with other types.
    let discovery = node.discovery();
    let mut members = discovery.live_members();
    members.push(discovery.local());
    pulicast::services_of(&members)
        .into_iter()
        .find(|s| s.name == service)?
        .servers
        .into_iter()
        .find(|e| e.node == server)
}

/// The reply of a call (its progress skipped), or the error that ended it.
async fn reply_of(call: &mut RawCall) -> Result<Vec<u8>, pulicast::Error> {
    loop {
        match call.next().await {
            Some(CallEvent::Progress(_)) => {}
            Some(CallEvent::Reply { message, .. }) => return Ok(message),
            Some(end) => return Err(call.error(end)),
            None => return Err(call.error(CallEvent::TimedOut)),
        }
    }
}

/// A client of a service: made by `Node.client` (`"double"`, or
/// `"double@node"` to call only that node's server).
///
/// Requests are encoded in the type the server announces: a Python value
/// for a 2.x primitive (an `int` for `int64_msg`, a `float` or `int` for
/// `double_msg`), dicts and lists for a native (Rust) type, `bytes` for
/// raw. Each call waits (the GIL released; Ctrl-C cancels it) up to its
/// timeout, the client's 5 s by default.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct Client {
    client: RawClient,
    node: pulicast::Node,
    timeout: Duration,
}

impl Client {
    pub(crate) fn new(
        ns: &pulicast::Namespace,
        node: &pulicast::Node,
        name: &str,
        timeout: f64,
    ) -> PyResult<Self> {
        let timeout = crate::bounded_seconds(timeout)?;
        let client = ns.raw_client(name).map_err(to_py)?;
        Ok(Self {
            client,
            node: node.clone(),
            timeout,
        })
    }

    fn within(&self, timeout: Option<f64>) -> PyResult<Duration> {
        timeout.map_or(Ok(self.timeout), crate::bounded_seconds)
    }

    /// Waits (up to `deadline`) for discovery to show a server of the
    /// service, and returns the types it announces.
    fn types(&self, py: Python<'_>, deadline: Instant, within: Duration) -> PyResult<ServiceEnd> {
        let (node, client) = (self.node.clone(), self.client.clone());
        crate::wait(py, found_types(node, client, deadline, within))?
    }

    /// Waits for the server's types (up to `within`), encodes `request`
    /// in them and starts the call; the types with it.
    fn start_call(
        &self,
        request: &Bound<'_, PyAny>,
        within: Duration,
    ) -> PyResult<(RawCall, ServiceEnd)> {
        let py = request.py();
        let deadline = Instant::now() + within;
        let end = self.types(py, deadline, within)?;
        let message = encode_as(request, end.request.as_ref())?;
        let client = self.client.clone();
        let left = deadline.saturating_duration_since(Instant::now());
        let call =
            crate::wait(py, async move { client.start(&message, left).await })?.map_err(to_py)?;
        Ok((call, end))
    }
}

/// Waits (up to `deadline`) for discovery to show a server of `client`'s
/// service, and returns the types it announces.
async fn found_types(
    node: pulicast::Node,
    client: RawClient,
    deadline: Instant,
    within: Duration,
) -> PyResult<ServiceEnd> {
    loop {
        if let Some(end) = announced(&node, &client) {
            return Ok(end);
        }
        if Instant::now() >= deadline {
            return Err(PulicastError::new_err(format!(
                "no server of {} found within {:.1} s",
                client.service(),
                within.as_secs_f64()
            )));
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// `message` of type `ty` as Python.
fn value_of<'py>(
    py: Python<'py>,
    message: &[u8],
    ty: Option<&pulicast::TypeInfo>,
) -> PyResult<Bound<'py, PyAny>> {
    if ty.is_none() {
        return Ok(PyBytes::new(py, message).into_any());
    }
    let known = ty.map(|ty| Known::new(ty.clone()));
    Ok(read(py, message, known.as_ref())?.1)
}

#[pymethods]
impl Client {
    /// The service's full name (with `@node` if the client targets one).
    #[getter]
    fn service(&self) -> String {
        self.client.service()
    }

    /// The nodes that serve it now, in the order calls try them.
    fn servers(&self, py: Python<'_>) -> Vec<String> {
        py.detach(|| self.client.servers())
    }

    /// A client of the nearest server instead: this node's configuration
    /// before none, each from the namespace out to the root; a server that
    /// does not answer is passed over for the next.
    fn nearest(&self) -> PyResult<Client> {
        Ok(Client {
            client: self.client.clone().nearest().map_err(to_py)?,
            node: self.node.clone(),
            timeout: self.timeout,
        })
    }

    /// Calls a server and returns its reply. A failure raises
    /// `PulicastError` with the server's words (a Python server's
    /// exception: its type and message).
    #[pyo3(signature = (request, timeout = None))]
    fn call<'py>(
        &self,
        request: &Bound<'py, PyAny>,
        timeout: Option<f64>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let py = request.py();
        let (mut call, end) = self.start_call(request, self.within(timeout)?)?;
        let reply = crate::wait(py, async move { reply_of(&mut call).await })?.map_err(to_py)?;
        value_of(py, &reply, end.reply.as_ref())
    }

    /// Like `call`, as an asyncio awaitable: `await client.call_async(21)`.
    /// Cancelling it cancels the call.
    #[pyo3(signature = (request, timeout = None))]
    fn call_async<'py>(
        &self,
        request: &Bound<'py, PyAny>,
        timeout: Option<f64>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let py = request.py();
        let within = self.within(timeout)?;
        let request = request.clone().unbind();
        let (node, client) = (self.node.clone(), self.client.clone());
        crate::awaitable(py, async move {
            let deadline = Instant::now() + within;
            let end = found_types(node, client.clone(), deadline, within).await?;
            let message = crate::attached(|py| encode_as(request.bind(py), end.request.as_ref()))?;
            let left = deadline.saturating_duration_since(Instant::now());
            let mut call = client.start(&message, left).await.map_err(to_py)?;
            let reply = reply_of(&mut call).await.map_err(to_py)?;
            crate::attached(|py| Ok(value_of(py, &reply, end.reply.as_ref())?.unbind()))
        })
    }

    /// Starts a call, to follow its progress and take its reply:
    /// `OngoingCall`. Dropping it (or `cancel()`) cancels the call.
    #[pyo3(signature = (request, timeout = None))]
    fn start(&self, request: &Bound<'_, PyAny>, timeout: Option<f64>) -> PyResult<OngoingCall> {
        let (call, end) = self.start_call(request, self.within(timeout)?)?;
        Ok(OngoingCall {
            node: call.node().to_string(),
            call: Arc::new(tokio::sync::Mutex::new(Some(call))),
            cancelled: tokio::sync::watch::channel(false).0,
            end,
            ended: Arc::default(),
            _node: self.node.clone(),
        })
    }

    /// Calls every server (once discovery knows one) and gathers each
    /// one's answer: `(node, reply, error)` tuples, `error` `None` where it
    /// replied and `reply` `None` where it did not.
    #[pyo3(signature = (request, timeout = None))]
    fn call_all<'py>(
        &self,
        request: &Bound<'py, PyAny>,
        timeout: Option<f64>,
    ) -> PyResult<Vec<Answer<'py>>> {
        let py = request.py();
        let within = self.within(timeout)?;
        let deadline = Instant::now() + within;
        // Encoded once, in the types of the server the client finds first.
        let end = self.types(py, deadline, within)?;
        let message = encode_as(request, end.request.as_ref())?;
        let client = self.client.clone();
        let left = deadline.saturating_duration_since(Instant::now());
        let answers = crate::wait(py, async move {
            let calls = client.start_all(&message, left).await?;
            let mut answers = Vec::with_capacity(calls.len());
            for (node, call) in calls {
                let answer = match call {
                    Ok(mut call) => reply_of(&mut call).await,
                    Err(e) => Err(e),
                };
                answers.push((node, answer));
            }
            Ok::<_, pulicast::Error>(answers)
        })?
        .map_err(to_py)?;
        answers
            .into_iter()
            .map(|(node, answer)| match answer {
                Ok(reply) => Ok((node, value_of(py, &reply, end.reply.as_ref())?, None)),
                Err(e) => Ok((node, py.None().into_bound(py), Some(e.to_string()))),
            })
            .collect()
    }

    fn __repr__(&self) -> String {
        format!("Client({:?})", self.client.service())
    }
}

/// One server's answer in `Client.call_all`: node, reply, error.
type Answer<'py> = (String, Bound<'py, PyAny>, Option<String>);

/// A call in flight: iterate it (or `progress()`) for its progress, then
/// `reply()`. Dropping it before its reply, or `cancel()`, cancels it.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct OngoingCall {
    /// `None` once it ended (or was cancelled); async-locked so a wait
    /// holds it across awaits on the waiting runtime.
    call: Arc<tokio::sync::Mutex<Option<RawCall>>>,
    /// Set by `cancel()`: a wait for the next event ends at once, so the
    /// call is let go of whoever waits on it.
    cancelled: tokio::sync::watch::Sender<bool>,
    node: String,
    end: ServiceEnd,
    /// The call's end, once `progress()` met it: for `reply()`.
    ended: Ended,
    _node: pulicast::Node,
}

/// What a call gives next: progress, or its end.
enum Next {
    Progress(Vec<u8>),
    Reply(Vec<u8>),
    Ended(pulicast::Error),
    Over,
}

/// The call's end, kept once a progress wait met it: for `reply()`.
type Ended = Arc<Mutex<Option<Result<Vec<u8>, pulicast::Error>>>>;

impl OngoingCall {
    /// The call's next event: progress (unless skipped), or its end.
    fn next_event(
        &self,
        skip_progress: bool,
    ) -> impl std::future::Future<Output = Next> + Send + 'static {
        let call = Arc::clone(&self.call);
        let mut cancelled = self.cancelled.subscribe();
        async move {
            let mut slot = call.lock().await;
            let Some(raw) = slot.as_mut() else {
                return Next::Over;
            };
            loop {
                let event = tokio::select! {
                    event = raw.next() => event,
                    _ = cancelled.wait_for(|c| *c) => {
                        *slot = None;
                        return Next::Over;
                    }
                };
                let next = match event {
                    Some(CallEvent::Progress(_)) if skip_progress => continue,
                    Some(CallEvent::Progress(p)) => return Next::Progress(p),
                    Some(CallEvent::Reply { message, .. }) => Next::Reply(message),
                    Some(end) => Next::Ended(raw.error(end)),
                    None => Next::Ended(raw.error(CallEvent::TimedOut)),
                };
                *slot = None;
                return next;
            }
        }
    }

    /// The progress value `next` brings, if any; keeps the call's end.
    fn progress_of(
        py: Python<'_>,
        next: Next,
        end: &ServiceEnd,
        ended: &Ended,
    ) -> PyResult<Option<Py<PyAny>>> {
        let kept = match next {
            Next::Progress(p) => {
                return Ok(Some(value_of(py, &p, end.progress.as_ref())?.unbind()))
            }
            Next::Reply(r) => Ok(r),
            Next::Ended(e) => Err(e),
            Next::Over => return Ok(None),
        };
        *crate::lock(ended) = Some(kept);
        Ok(None)
    }

    /// The reply: the end kept, or the one `next` brings.
    fn reply_of(
        py: Python<'_>,
        ended: Result<Vec<u8>, pulicast::Error>,
        end: &ServiceEnd,
    ) -> PyResult<Py<PyAny>> {
        Ok(value_of(py, &ended.map_err(to_py)?, end.reply.as_ref())?.unbind())
    }

    /// The call's end: kept by a progress wait, or the one `next` brings
    /// (taken when the wait ends, so a progress reader that met the end
    /// meanwhile leaves it here).
    fn ended_of(next: Next, ended: &Ended) -> PyResult<Result<Vec<u8>, pulicast::Error>> {
        match next {
            Next::Reply(r) => Ok(Ok(r)),
            Next::Ended(e) => Ok(Err(e)),
            Next::Progress(_) | Next::Over => crate::lock(ended)
                .take()
                .ok_or_else(|| PulicastError::new_err("the call's reply was taken already")),
        }
    }

    /// The reply, once the call ended: what a progress wait kept, or what
    /// comes next (progress skipped).
    fn ended(
        &self,
    ) -> impl std::future::Future<Output = PyResult<Result<Vec<u8>, pulicast::Error>>> + Send + 'static
    {
        let next = self.next_event(true);
        let ended = Arc::clone(&self.ended);
        async move {
            // Looked at when the wait runs, not when it was made: a
            // reply_async() made before the progress ran out sees its end.
            let kept = crate::lock(&ended).take();
            match kept {
                Some(kept) => Ok(kept),
                None => Self::ended_of(next.await, &ended),
            }
        }
    }
}

#[pymethods]
impl OngoingCall {
    /// The server node the call went to.
    #[getter]
    fn node(&self) -> String {
        self.node.clone()
    }

    /// The next progress message; `None` once the call ended (take its
    /// reply with `reply()`).
    fn progress(&self, py: Python<'_>) -> PyResult<Option<Py<PyAny>>> {
        let next = crate::wait(py, self.next_event(false))?;
        Self::progress_of(py, next, &self.end, &self.ended)
    }

    /// `progress` as an asyncio awaitable.
    fn progress_async<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let next = self.next_event(false);
        let (end, ended) = (self.end.clone(), Arc::clone(&self.ended));
        crate::awaitable(py, async move {
            let next = next.await;
            crate::attached(|py| Self::progress_of(py, next, &end, &ended))
        })
    }

    /// The reply (progress not taken yet is skipped); `PulicastError` if
    /// the call failed, timed out or was cancelled.
    fn reply(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        let ended = crate::wait(py, self.ended())??;
        Self::reply_of(py, ended, &self.end)
    }

    /// `reply` as an asyncio awaitable.
    fn reply_async<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let (ended, end) = (self.ended(), self.end.clone());
        crate::awaitable(py, async move {
            let ended = ended.await?;
            crate::attached(|py| Self::reply_of(py, ended, &end))
        })
    }

    /// Cancels the call: the server's handler is told.
    fn cancel(&self, py: Python<'_>) -> PyResult<()> {
        self.cancelled.send_replace(true);
        let call = Arc::clone(&self.call);
        crate::wait(py, async move { drop(call.lock().await.take()) })
    }

    fn __iter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    fn __next__(&self, py: Python<'_>) -> PyResult<Option<Py<PyAny>>> {
        self.progress(py)
    }

    /// `async for progress in call`: ends when the call does.
    fn __aiter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    fn __anext__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let next = self.next_event(false);
        let (end, ended) = (self.end.clone(), Arc::clone(&self.ended));
        crate::awaitable(py, async move {
            let next = next.await;
            crate::attached(|py| Self::progress_of(py, next, &end, &ended))?
                .ok_or_else(|| pyo3::exceptions::PyStopAsyncIteration::new_err(()))
        })
    }
}

/// `@node.serve("double")`: what serves the function it decorates (the
/// decorated name is then the `Server`: keep it).
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct Serving {
    ns: pulicast::Namespace,
    node: pulicast::Node,
    name: String,
    request: Option<Py<PyAny>>,
    reply: Option<Py<PyAny>>,
    progress: Option<Py<PyAny>>,
    concurrency: Option<usize>,
}

#[pymethods]
impl Serving {
    fn __call__(&self, func: &Bound<'_, PyAny>) -> PyResult<Server> {
        let py = func.py();
        let bound = |t: &Option<Py<PyAny>>| t.as_ref().map(|t| t.bind(py).clone());
        serve(
            &self.ns,
            &self.node,
            &self.name,
            func,
            bound(&self.request).as_ref(),
            bound(&self.reply).as_ref(),
            bound(&self.progress).as_ref(),
            self.concurrency,
        )
    }
}

/// `serve(name, handler=None, ...)` of a node or namespace: the server, or
/// with no handler the decorator that makes it.
#[allow(clippy::too_many_arguments)]
pub(crate) fn serve_or_decorate(
    py: Python<'_>,
    ns: &pulicast::Namespace,
    node: &pulicast::Node,
    name: &str,
    handler: Option<Bound<'_, PyAny>>,
    request: Option<Bound<'_, PyAny>>,
    reply: Option<Bound<'_, PyAny>>,
    progress: Option<Bound<'_, PyAny>>,
    concurrency: Option<usize>,
) -> PyResult<Py<PyAny>> {
    match handler {
        Some(func) => {
            let server = serve(
                ns,
                node,
                name,
                &func,
                request.as_ref(),
                reply.as_ref(),
                progress.as_ref(),
                concurrency,
            )?;
            Ok(Py::new(py, server)?.into_any())
        }
        None => {
            let serving = Serving {
                ns: ns.clone(),
                node: node.clone(),
                name: name.to_string(),
                request: request.map(Bound::unbind),
                reply: reply.map(Bound::unbind),
                progress: progress.map(Bound::unbind),
                concurrency,
            };
            Ok(Py::new(py, serving)?.into_any())
        }
    }
}

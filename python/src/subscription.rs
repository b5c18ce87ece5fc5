//! Messages and subscriptions: received messages decoded by the type
//! their channel announces, a blocking receive that lets Ctrl-C through,
//! and callbacks on a thread of their own that the node never waits for.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use std::net::SocketAddr;

use pulicast::Bytes;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyBytes, PyString};

use crate::convert::Known;

use crate::{to_py, SIGNAL_CHECK};

/// One received message. Its value is decoded when first read, so a
/// consumer that counts, forwards or filters messages by their channel
/// or source pays for no decoding.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct Message {
    payload: Bytes,
    /// The type announced on its channel when it came, if any.
    known: Option<Arc<Known>>,
    /// `(type_name, value)`, once read.
    decoded: PyOnceLock<(Py<PyString>, Py<PyAny>)>,
    source: SocketAddr,
    /// The message's lead: 1 in order, more after losses, 0 or less late
    /// or repeated.
    #[pyo3(get)]
    lead: i64,
    /// The sender's sequence number on the channel.
    #[pyo3(get)]
    seq: u32,
    /// The channel it came on (one string for all its messages).
    #[pyo3(get)]
    channel: Py<PyString>,
}

impl Message {
    fn decoded(&self, py: Python<'_>) -> PyResult<&(Py<PyString>, Py<PyAny>)> {
        self.decoded.get_or_try_init(py, || {
            let (name, value) = crate::convert::read(py, &self.payload, self.known.as_deref())?;
            Ok((PyString::new(py, &name).unbind(), value.unbind()))
        })
    }
}

#[pymethods]
impl Message {
    /// The value: `bool`, `int`, `float`, `str` for 2.x primitives; a
    /// dict/list for a native type its channel announces; `bytes` for
    /// anything else.
    #[getter]
    fn value(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        Ok(self.decoded(py)?.1.clone_ref(py))
    }

    /// The type it was read as (`double_msg`, `Pose`, `bytes`).
    #[getter]
    fn type_name(&self, py: Python<'_>) -> PyResult<Py<PyString>> {
        Ok(self.decoded(py)?.0.clone_ref(py))
    }

    /// The sender's address, `"ip:port"`.
    #[getter]
    fn source(&self) -> String {
        self.source.to_string()
    }

    /// The payload as it came (a 2.x or native message's fingerprint
    /// first), as `bytes`, for readers of their own (ZCM classes).
    #[getter]
    fn payload<'py>(&self, py: Python<'py>) -> Bound<'py, PyBytes> {
        PyBytes::new(py, &self.payload)
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        let (type_name, value) = match self.decoded(py) {
            Ok((name, value)) => (
                name.bind(py).to_string(),
                value
                    .bind(py)
                    .repr()
                    .map_or_else(|_| "?".to_string(), |r| r.to_string()),
            ),
            Err(_) => ("?".to_string(), "?".to_string()),
        };
        format!(
            "Message(channel={:?}, value={value}, type_name={type_name:?}, source={:?}, lead={}, seq={})",
            self.channel.bind(py).to_string(),
            self.source.to_string(),
            self.lead,
            self.seq
        )
    }
}

/// What a channel's messages are read as: the type its publishers
/// announce, looked up again when a message of another type comes.
#[derive(Clone)]
struct Reader {
    channel: pulicast::Channel,
    /// The channel's name, made once for every message to share.
    name: Arc<Py<PyString>>,
    announced: Arc<Mutex<Announced>>,
}

/// The type last looked up in discovery for a fingerprint (`None`: none
/// announced), and when: a miss is looked up again after
/// [`LOOK_AGAIN`], not for every message.
#[derive(Default)]
struct Announced {
    fingerprint: Option<[u8; 8]>,
    known: Option<Arc<Known>>,
    looked: Option<Instant>,
}

/// How long a fingerprint that no publisher announces is taken for one
/// without a type before discovery is asked again.
const LOOK_AGAIN: Duration = Duration::from_millis(100);

impl Reader {
    fn new(py: Python<'_>, channel: &pulicast::Channel) -> Self {
        Self {
            channel: channel.clone(),
            name: Arc::new(PyString::new(py, channel.name()).unbind()),
            announced: Arc::default(),
        }
    }

    /// The type announced for a payload with `fingerprint`, if any
    /// publisher announces it.
    fn announced_for(&self, fingerprint: Option<[u8; 8]>) -> Option<Arc<Known>> {
        let fingerprint = fingerprint?;
        let mut announced = self
            .announced
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let stale = announced.fingerprint != Some(fingerprint)
            || (announced.known.is_none()
                && announced.looked.is_none_or(|at| at.elapsed() >= LOOK_AGAIN));
        if stale {
            let name = self.channel.name();
            announced.known = self
                .channel
                .publishers()
                .into_iter()
                .flat_map(|m| m.channels)
                .filter(|c| c.name == name)
                .filter_map(|c| c.message_type)
                .find(|t| t.fingerprint == fingerprint)
                .map(|info| Arc::new(Known::new(info)));
            announced.fingerprint = Some(fingerprint);
            announced.looked = Some(Instant::now());
        }
        announced.known.clone()
    }

    /// The message, its value left to be decoded when read.
    fn read(&self, py: Python<'_>, m: pulicast::Message<Bytes>) -> Message {
        let fingerprint = pulicast::Fingerprint::of_payload(&m.value);
        // 2.x primitives need no announcement.
        let known = match fingerprint.and_then(pulicast::PrimitiveKind::from_fingerprint) {
            Some(_) => None,
            None => self.announced_for(fingerprint.map(|f| f.0)),
        };
        Message {
            payload: m.value,
            known,
            decoded: PyOnceLock::new(),
            source: m.source,
            lead: m.lead,
            seq: m.seq,
            channel: self.name.clone_ref(py),
        }
    }
}

/// How often a receive looks again while another thread waits on the
/// same subscription.
const BUSY_POLL: Duration = Duration::from_millis(10);

/// A subscription, and whether it was closed. A receiving thread takes
/// the subscription out for its wait, so the lock is never held across a
/// wait: on a `start_blocking` node, the waiting thread runs the node's
/// callbacks, and one of them may close this very subscription.
struct Slot {
    subscription: Option<pulicast::Subscription<Bytes>>,
    closed: bool,
}

/// What [`Subscription::with_taken`] found.
enum Taken<R> {
    Got(R),
    /// Another thread has it.
    Busy,
    Closed,
}

fn lock_slot(slot: &Mutex<Slot>) -> std::sync::MutexGuard<'_, Slot> {
    slot.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Subscription {
    /// Runs `f` on the subscription, taken out of its slot meanwhile; puts
    /// it back unless it was closed meanwhile (then drops it: unsubscribes).
    fn with_taken<R>(&self, f: impl FnOnce(&mut pulicast::Subscription<Bytes>) -> R) -> Taken<R> {
        let taken = {
            let mut slot = lock_slot(&self.slot);
            if slot.closed {
                return Taken::Closed;
            }
            slot.subscription.take()
        };
        let Some(mut subscription) = taken else {
            return Taken::Busy;
        };
        let result = f(&mut subscription);
        let mut slot = lock_slot(&self.slot);
        if slot.closed {
            drop(slot);
            drop(subscription);
        } else {
            slot.subscription = Some(subscription);
        }
        Taken::Got(result)
    }
}

/// A subscription to receive from: `recv(timeout)`, or iterate it.
/// `close()` (or dropping it) unsubscribes.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct Subscription {
    slot: Arc<Mutex<Slot>>,
    reader: Reader,
    /// Kept so the node runs while the subscription is used.
    node: pulicast::Node,
}

impl Subscription {
    pub(crate) fn new(
        py: Python<'_>,
        channel: &pulicast::Channel,
        node: &pulicast::Node,
    ) -> PyResult<Self> {
        let subscription = py.detach(|| channel.subscribe_raw()).map_err(to_py)?;
        Ok(Self {
            slot: Arc::new(Mutex::new(Slot {
                subscription: Some(subscription),
                closed: false,
            })),
            reader: Reader::new(py, channel),
            node: node.clone(),
        })
    }

    /// Waits up to `timeout` (forever: `None`) for a message, in slices
    /// that let signals through.
    fn wait(&self, py: Python<'_>, timeout: Option<Duration>) -> PyResult<Option<Message>> {
        let got = self.wait_with(py, timeout, |s, slice| s.recv_timeout(slice))?;
        Ok(got.map(|m| self.reader.read(py, m)))
    }

    /// Waits up to `timeout` (forever: `None`) until `take` takes something
    /// from the subscription (it waits up to the slice it is given), in
    /// slices that let signals through; `None` on time out, at the end, or
    /// once the subscription closed.
    fn wait_with<R: Send>(
        &self,
        py: Python<'_>,
        timeout: Option<Duration>,
        mut take: impl FnMut(&mut pulicast::Subscription<Bytes>, Duration) -> Option<R> + Send,
    ) -> PyResult<Option<R>> {
        // A deadline past what the clock holds is none.
        let deadline = timeout.and_then(|t| Instant::now().checked_add(t));
        loop {
            let slice = match deadline {
                Some(at) => at
                    .saturating_duration_since(Instant::now())
                    .min(SIGNAL_CHECK),
                None => SIGNAL_CHECK,
            };
            let got = py.detach(|| match self.with_taken(|s| take(s, slice)) {
                Taken::Busy => {
                    // Another thread waits on it: look again soon.
                    std::thread::sleep(slice.min(BUSY_POLL));
                    Taken::Busy
                }
                other => other,
            });
            match got {
                Taken::Got(Some(got)) => return Ok(Some(got)),
                Taken::Closed => return Ok(None),
                Taken::Got(None) | Taken::Busy => {}
            }
            py.check_signals()?;
            let exiting = crate::is_exiting();
            if exiting || deadline.is_some_and(|at| Instant::now() >= at) || self.node.is_stopped()
            {
                return Ok(None);
            }
        }
    }
}

/// A subscription taken out of its slot by an async wait: put back when
/// the wait ends, or is cancelled (dropped), unless it was closed.
struct TakenOut {
    slot: Arc<Mutex<Slot>>,
    subscription: Option<pulicast::Subscription<Bytes>>,
}

impl Drop for TakenOut {
    fn drop(&mut self) {
        let mut slot = lock_slot(&self.slot);
        let subscription = self.subscription.take();
        if slot.closed {
            drop(slot);
            drop(subscription);
        } else {
            slot.subscription = subscription;
        }
    }
}

impl Subscription {
    /// The next message, waited for on the waiting runtime (for asyncio):
    /// `None` at the end or once `timeout` passed.
    fn next_async(
        &self,
        timeout: Option<Duration>,
    ) -> impl std::future::Future<Output = PyResult<Option<Message>>> + Send + 'static {
        let slot = Arc::clone(&self.slot);
        let reader = self.reader.clone();
        let deadline = timeout.and_then(|t| tokio::time::Instant::now().checked_add(t));
        async move {
            let got = loop {
                let taken = {
                    let mut s = lock_slot(&slot);
                    if s.closed {
                        return Ok(None);
                    }
                    s.subscription.take()
                };
                let Some(subscription) = taken else {
                    // Another wait has it: look again soon.
                    if deadline.is_some_and(|d| tokio::time::Instant::now() >= d) {
                        return Ok(None);
                    }
                    tokio::time::sleep(BUSY_POLL).await;
                    continue;
                };
                let mut out = TakenOut {
                    slot: Arc::clone(&slot),
                    subscription: Some(subscription),
                };
                let Some(subscription) = out.subscription.as_mut() else {
                    return Ok(None);
                };
                // In slices, to see a close from another thread.
                break loop {
                    let now = tokio::time::Instant::now();
                    let slice_end = match deadline {
                        Some(d) if d <= now => break None,
                        Some(d) => d.min(now + SIGNAL_CHECK),
                        None => now + SIGNAL_CHECK,
                    };
                    if let Ok(got) = tokio::time::timeout_at(slice_end, subscription.recv()).await {
                        break got;
                    }
                    if lock_slot(&slot).closed {
                        break None;
                    }
                };
            };
            match got {
                Some(m) => crate::attached(|py| Ok(reader.read(py, m))).map(Some),
                None => Ok(None),
            }
        }
    }
}

#[pymethods]
impl Subscription {
    /// The next message, waiting up to `timeout` seconds (`None`: until one
    /// comes); `None` if none came in time, or once the node stopped or the
    /// subscription closed. Ctrl-C interrupts the wait.
    #[pyo3(signature = (timeout = None))]
    fn recv(&self, py: Python<'_>, timeout: Option<f64>) -> PyResult<Option<Message>> {
        let timeout = timeout.map(seconds).transpose()?;
        self.wait(py, timeout)
    }

    /// Up to `max` messages at once: those queued, or once one comes
    /// (within `timeout` seconds; `None`: until one does), all that are
    /// queued then. An empty list if none came in time, or once the node
    /// stopped or the subscription closed. Ctrl-C interrupts the wait.
    #[pyo3(signature = (max, timeout = None))]
    fn recv_many(
        &self,
        py: Python<'_>,
        max: usize,
        timeout: Option<f64>,
    ) -> PyResult<Vec<Message>> {
        if max == 0 {
            return Err(pyo3::exceptions::PyValueError::new_err(
                "max must be at least 1",
            ));
        }
        let timeout = timeout.map(seconds).transpose()?;
        // All that is queued in one take, decoded only when read.
        let took = self.wait_with(py, timeout, |s, slice| {
            let mut taken = Vec::new();
            (s.recv_many_timeout(&mut taken, max, slice) > 0).then_some(taken)
        })?;
        Ok(took
            .unwrap_or_default()
            .into_iter()
            .map(|m| self.reader.read(py, m))
            .collect())
    }

    /// The channel's name.
    #[getter]
    fn channel(&self) -> String {
        self.reader.channel.name().to_string()
    }

    /// Unsubscribes; `recv` then returns `None`. A receive waiting in
    /// another thread (or this one, from a callback) returns `None` after
    /// its current slice.
    fn close(&self, py: Python<'_>) {
        py.detach(|| {
            let closed = {
                let mut slot = lock_slot(&self.slot);
                slot.closed = true;
                slot.subscription.take()
            };
            drop(closed);
        });
    }

    /// Like `recv`, as an asyncio awaitable: `await sub.recv_async(1.0)`.
    /// Cancelling it leaves the subscription as it was.
    #[pyo3(signature = (timeout = None))]
    fn recv_async<'py>(
        &self,
        py: Python<'py>,
        timeout: Option<f64>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let timeout = timeout.map(crate::bounded_seconds).transpose()?;
        crate::awaitable(py, self.next_async(timeout))
    }

    /// `async for message in sub`: ends when the node stops or the
    /// subscription is closed.
    fn __aiter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    fn __anext__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let next = self.next_async(None);
        crate::awaitable(py, async move {
            next.await?
                .ok_or_else(|| pyo3::exceptions::PyStopAsyncIteration::new_err(()))
        })
    }

    fn __iter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    fn __next__(&self, py: Python<'_>) -> PyResult<Option<Message>> {
        self.wait(py, None)
    }

    fn __enter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    #[pyo3(signature = (*_args))]
    fn __exit__(&self, py: Python<'_>, _args: &Bound<'_, pyo3::types::PyTuple>) {
        self.close(py);
    }
}

/// A subscription whose callback runs on a thread of its own (see [`dispatch`]).
/// `close()` (or dropping it) unsubscribes.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct CallbackSubscription {
    state: Arc<Dispatch>,
    channel: String,
    /// Kept so the node runs while the subscription is used.
    _node: pulicast::Node,
}

/// What a callback subscription's thread and its Python object share.
struct Dispatch {
    /// Set by `close()` (or dropping the object): no callback starts
    /// after it; the thread ends within a slice and unsubscribes.
    closed: AtomicBool,
    errors: AtomicU64,
}

/// Messages a callback thread takes per turn of the GIL, at most.
const DISPATCH_BATCH: usize = 256;

impl CallbackSubscription {
    pub(crate) fn new(
        py: Python<'_>,
        channel: &pulicast::Channel,
        node: &pulicast::Node,
        callback: Py<PyAny>,
    ) -> PyResult<Self> {
        if !callback.bind(py).is_callable() {
            return Err(pyo3::exceptions::PyTypeError::new_err(
                "callback must be callable: it is called with each message",
            ));
        }
        let state = Arc::new(Dispatch {
            closed: AtomicBool::new(false),
            errors: AtomicU64::new(0),
        });
        let mut subscription = py.detach(|| channel.subscribe_raw()).map_err(to_py)?;
        // The thread holds the channel (through the reader), not the node:
        // a node holding its own callback's node would never stop when the
        // program lets it go.
        let reader = Reader::new(py, channel);
        let name = channel.name().to_string();
        let shared = Arc::clone(&state);
        std::thread::Builder::new()
            .name(format!("pulicast_rs {name}"))
            .spawn(move || {
                dispatch(&mut subscription, &reader, &callback, &shared, &name);
                // Unsubscribed without the GIL; the callback let go with it.
                drop(subscription);
                crate::with_python(move |_| drop(callback));
            })
            .map_err(|e| {
                crate::PulicastError::new_err(format!("no thread for the callback: {e}"))
            })?;
        Ok(Self {
            state,
            channel: channel.name().to_string(),
            _node: node.clone(),
        })
    }
}

/// A callback subscription's thread: waits for messages without the GIL,
/// then takes it once for all that came (up to [`DISPATCH_BATCH`]) and
/// calls the callback with each. Off the node's receive path, a callback
/// may block: call a service, wait for a setting, close itself.
fn dispatch(
    subscription: &mut pulicast::Subscription<Bytes>,
    reader: &Reader,
    callback: &Py<PyAny>,
    state: &Dispatch,
    name: &str,
) {
    let mut batch = Vec::with_capacity(DISPATCH_BATCH);
    loop {
        if state.closed.load(Ordering::SeqCst) || crate::is_exiting() {
            return;
        }
        batch.clear();
        if subscription.recv_many_timeout(&mut batch, DISPATCH_BATCH, SIGNAL_CHECK) == 0 {
            if subscription.is_finished() {
                return;
            }
            continue;
        }
        crate::with_python(|py| {
            for m in batch.drain(..) {
                // Checked with the GIL held, as `close()` sets it: once
                // `close()` returned, no call starts.
                if state.closed.load(Ordering::SeqCst) {
                    return;
                }
                let called = callback.call1(py, (reader.read(py, m),));
                if let Err(e) = called {
                    // Counted and shown, never raised into the node.
                    state.errors.fetch_add(1, Ordering::Relaxed);
                    eprintln!("pulicast_rs: the callback of {name} raised:");
                    e.display(py);
                }
            }
        });
    }
}

impl Drop for CallbackSubscription {
    fn drop(&mut self) {
        self.state.closed.store(true, Ordering::SeqCst);
    }
}

#[pymethods]
impl CallbackSubscription {
    /// How many times the callback raised (each shown on stderr).
    #[getter]
    fn errors(&self) -> u64 {
        self.state.errors.load(Ordering::Relaxed)
    }

    /// The channel's name.
    #[getter]
    fn channel(&self) -> String {
        self.channel.clone()
    }

    /// Unsubscribes: once it returns, the callback is not called again
    /// (a call running in another thread finishes). A callback may close
    /// its own subscription.
    fn close(&self) {
        self.state.closed.store(true, Ordering::SeqCst);
    }

    fn __enter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    #[pyo3(signature = (*_args))]
    fn __exit__(&self, _args: &Bound<'_, pyo3::types::PyTuple>) {
        self.close();
    }
}

/// `secs` as a duration; `ValueError` if negative or not finite.
pub(crate) fn seconds(secs: f64) -> PyResult<Duration> {
    Duration::try_from_secs_f64(secs).map_err(|_| {
        pyo3::exceptions::PyValueError::new_err(format!(
            "expected a finite number of seconds >= 0, not {secs}"
        ))
    })
}

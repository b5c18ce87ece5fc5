//! The native module of the `pulicast_rs` Python package (`pulicast_rs._native`):
//! pulicast's public API, for Python. The pure-Python package around it
//! (`python/pulicast_rs/`) re-exports it; `docs/python.md` is the guide.
//!
//! Rules that hold for every class here:
//! - Whatever may wait (starting a node, a blocking receive, publishing,
//!   unsubscribing) runs with the GIL released (`py.detach`), so other
//!   Python threads and the node's own callbacks go on meanwhile.
//! - A blocking receive waits in slices of 100 ms and checks for
//!   signals between them, so Ctrl-C interrupts it in the main thread.
//! - Bad arguments raise `TypeError`/`ValueError` with what is wrong; the
//!   node's own errors raise `PulicastError`, with pulicast's message.

use std::future::Future;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use pyo3::prelude::*;

mod channel;
mod convert;
mod discovery;
mod node;
mod service;
mod setting;
mod subscription;

pyo3::create_exception!(
    _native,
    PulicastError,
    pyo3::exceptions::PyException,
    "An error of the pulicast node (a name it refuses, a stopped node, a socket that failed)."
);

/// How long a blocking receive waits before it checks for signals (Ctrl-C).
pub(crate) const SIGNAL_CHECK: Duration = Duration::from_millis(100);

/// Set by the package's `atexit` hook: from then on no callback starts.
/// A node's threads outlive the interpreter's finalization, and a thread
/// that takes the GIL during it aborts the process.
static EXITING: AtomicBool = AtomicBool::new(false);

/// Callbacks running now (the exit hook waits for them).
static RUNNING: AtomicUsize = AtomicUsize::new(0);

/// The longest the exit hook waits for running callbacks.
const EXIT_WAIT: Duration = Duration::from_secs(5);

/// Runs `f` with the GIL from one of the node's threads, unless the
/// interpreter is exiting (then nothing runs).
pub(crate) fn with_python(f: impl for<'py> FnOnce(Python<'py>)) {
    if EXITING.load(Ordering::SeqCst) {
        return;
    }
    RUNNING.fetch_add(1, Ordering::SeqCst);
    // Checked again once counted: the hook either sees this callback
    // running, or this callback sees the hook's flag.
    if !EXITING.load(Ordering::SeqCst) {
        let _ = Python::try_attach(f);
    }
    RUNNING.fetch_sub(1, Ordering::SeqCst);
}

/// Whether the interpreter is exiting: callback threads end.
pub(crate) fn is_exiting() -> bool {
    EXITING.load(Ordering::SeqCst)
}

/// `_exiting()`: the package's `atexit` hook. No callback starts from
/// now on; those running finish (within 5 s) with the GIL released here.
#[pyfunction]
fn _exiting(py: Python<'_>) {
    EXITING.store(true, Ordering::SeqCst);
    py.detach(|| {
        let deadline = Instant::now() + EXIT_WAIT;
        while RUNNING.load(Ordering::SeqCst) > 0 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(1));
        }
    });
}

/// The runtime the blocking calls of Python wait on (settings, service
/// calls): a thread of its own, so a wait works from any thread, a node's
/// callback included (a runtime can't be started inside another's).
static WAITING: OnceLock<&'static tokio::runtime::Runtime> = OnceLock::new();

/// The runtime the package waits on (made at first use), which also runs
/// the futures behind asyncio awaitables.
pub(crate) fn waiting_runtime() -> PyResult<&'static tokio::runtime::Runtime> {
    if let Some(r) = WAITING.get() {
        return Ok(*r);
    }
    // Made once, and handed to pyo3-async-runtimes before any other thread
    // can see it: an awaitable never runs on a runtime of its own.
    static MAKING: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _making = lock(&MAKING);
    if let Some(r) = WAITING.get() {
        return Ok(*r);
    }
    let built = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("pulicast_rs-wait")
        .enable_time()
        .build()
        .map_err(|e| PulicastError::new_err(format!("no runtime to wait on: {e}")))?;
    let runtime: &'static tokio::runtime::Runtime = Box::leak(Box::new(built));
    let _ = pyo3_async_runtimes::tokio::init_with_runtime(runtime);
    let _ = WAITING.set(runtime);
    Ok(runtime)
}

/// Runs `f` with the GIL in a future on the waiting runtime; an error once
/// the interpreter exits (attaching then would abort the process).
pub(crate) fn attached<T>(f: impl for<'py> FnOnce(Python<'py>) -> PyResult<T>) -> PyResult<T> {
    if is_exiting() {
        return Err(PulicastError::new_err("the program is exiting"));
    }
    Python::try_attach(f).unwrap_or_else(|| Err(PulicastError::new_err("the program is exiting")))
}

/// `fut` as an asyncio awaitable (of the running event loop), run on the
/// waiting runtime; cancelling the awaitable drops `fut`.
pub(crate) fn awaitable<'py, T>(
    py: Python<'py>,
    fut: impl Future<Output = PyResult<T>> + Send + 'static,
) -> PyResult<Bound<'py, PyAny>>
where
    T: for<'a> IntoPyObject<'a> + Send + 'static,
{
    waiting_runtime()?;
    pyo3_async_runtimes::tokio::future_into_py(py, fut)
}

/// Runs `fut` to its end on the waiting runtime while this thread waits
/// with the GIL released; Ctrl-C (a pending signal) drops `fut` (a call
/// is cancelled) and raises `KeyboardInterrupt`.
pub(crate) fn wait<T: Send + 'static>(
    py: Python<'_>,
    fut: impl Future<Output = T> + Send + 'static,
) -> PyResult<T> {
    let runtime = waiting_runtime()?;
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    let task = runtime.spawn(async move {
        let _ = tx.send(fut.await);
    });
    py.detach(move || loop {
        match rx.recv_timeout(Duration::from_millis(100)) {
            Ok(done) => return Ok(done),
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                // Never attach while the interpreter exits: give up.
                if is_exiting() {
                    task.abort();
                    return Err(PulicastError::new_err("the program is exiting"));
                }
                if let Err(e) = Python::attach(|py| py.check_signals()) {
                    task.abort();
                    return Err(e);
                }
            }
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                return Err(PulicastError::new_err("the wait ended without an answer"));
            }
        }
    })
}

/// The longest a call or a settings request waits: a timeout beyond it
/// (`1e19` seconds) is this, not a deadline past what the clock holds.
const LONGEST_WAIT: Duration = Duration::from_secs(30 * 24 * 3600);

/// `secs` as a duration for a timeout of a call or request, at most
/// [`LONGEST_WAIT`]; `ValueError` if negative or not finite.
pub(crate) fn bounded_seconds(secs: f64) -> PyResult<Duration> {
    Ok(subscription::seconds(secs)?.min(LONGEST_WAIT))
}

/// Locks `m`, going on after a panic elsewhere (what it guards stays
/// whole: each holder only takes or puts a value).
pub(crate) fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// pulicast's error as a Python exception: names and arguments as
/// `ValueError`, everything else as `PulicastError`.
pub(crate) fn to_py(e: pulicast::Error) -> PyErr {
    match e {
        pulicast::Error::InvalidName { .. } | pulicast::Error::InvalidConfig { .. } => {
            pyo3::exceptions::PyValueError::new_err(e.to_string())
        }
        e => PulicastError::new_err(e.to_string()),
    }
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("PulicastError", m.py().get_type::<PulicastError>())?;
    m.add("DEFAULT_PORT", pulicast::DEFAULT_PORT)?;
    m.add_class::<node::Node>()?;
    m.add_class::<channel::Namespace>()?;
    m.add_class::<channel::Channel>()?;
    m.add_class::<subscription::Message>()?;
    m.add_class::<subscription::Subscription>()?;
    m.add_class::<subscription::CallbackSubscription>()?;
    m.add_class::<setting::Setting>()?;
    m.add_class::<setting::SettingInfo>()?;
    m.add_class::<setting::FleetSettings>()?;
    m.add_class::<service::Server>()?;
    m.add_class::<service::Call>()?;
    m.add_class::<service::Client>()?;
    m.add_class::<service::OngoingCall>()?;
    m.add_class::<service::Serving>()?;
    m.add_class::<discovery::DiscoveryEvents>()?;
    m.add_class::<discovery::DiscoveryEventView>()?;
    m.add_function(wrap_pyfunction!(convert::encode, m)?)?;
    m.add_function(wrap_pyfunction!(convert::decode, m)?)?;
    m.add_function(wrap_pyfunction!(_exiting, m)?)?;
    Ok(())
}

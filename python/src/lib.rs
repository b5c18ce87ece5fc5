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

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use pyo3::prelude::*;

mod channel;
mod convert;
mod node;
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
    m.add_function(wrap_pyfunction!(convert::encode, m)?)?;
    m.add_function(wrap_pyfunction!(convert::decode, m)?)?;
    m.add_function(wrap_pyfunction!(_exiting, m)?)?;
    Ok(())
}

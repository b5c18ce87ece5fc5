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

use pyo3::prelude::*;

mod channel;
mod convert;
mod node;
mod subscription;

pyo3::create_exception!(
    _native,
    PulicastError,
    pyo3::exceptions::PyException,
    "An error of the pulicast node (a name it refuses, a stopped node, a socket that failed)."
);

/// How long a blocking receive waits before it checks for signals (Ctrl-C).
pub(crate) const SIGNAL_CHECK: std::time::Duration = std::time::Duration::from_millis(100);

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
    m.add_function(wrap_pyfunction!(convert::encode, m)?)?;
    m.add_function(wrap_pyfunction!(convert::decode, m)?)?;
    Ok(())
}

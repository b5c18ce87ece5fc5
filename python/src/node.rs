//! `Node`: a pulicast node, started when made.

use std::net::Ipv4Addr;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::channel::{Channel, Namespace};
use crate::to_py;

/// A pulicast node: `Node("rover_controller", namespace="rover1")`.
///
/// It starts when made (its sockets open, discovery begins) and runs on
/// threads of its own until `stop()` (or the end of a `with` block, or the
/// interpreter's exit). Channels are named as in Rust: relative to the
/// node's namespace, or absolute with a leading `/`.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct Node {
    pub(crate) node: pulicast::Node,
}

#[pymethods]
impl Node {
    #[new]
    #[pyo3(signature = (name, namespace = "", *, port = None, interface = None, ttl = None, config = None, heartbeat_period = None, keys_from_env = true))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        name: &str,
        namespace: &str,
        port: Option<u16>,
        interface: Option<&str>,
        ttl: Option<u32>,
        config: Option<String>,
        heartbeat_period: Option<f64>,
        keys_from_env: bool,
    ) -> PyResult<Self> {
        let mut builder = pulicast::Node::new(name)
            .namespace(namespace)
            .keys_from_env(keys_from_env);
        if let Some(port) = port {
            builder = builder.port(port);
        }
        if let Some(interface) = interface {
            let address: Ipv4Addr = interface.parse().map_err(|_| {
                PyValueError::new_err(format!(
                    "interface {interface:?} is not an IPv4 address (such as \"127.0.0.1\")"
                ))
            })?;
            builder = builder.interface(address);
        }
        if let Some(ttl) = ttl {
            builder = builder.ttl(ttl);
        }
        if let Some(config) = config {
            builder = builder.config(config);
        }
        if let Some(period) = heartbeat_period {
            builder = builder.heartbeat_period(crate::subscription::seconds(period)?);
        }
        let node = py.detach(|| builder.start_blocking()).map_err(to_py)?;
        Ok(Self { node })
    }

    /// The node's name.
    #[getter]
    fn name(&self) -> String {
        self.node.name().to_string()
    }

    /// The node's namespace (`""` for the root).
    #[getter]
    fn namespace(&self) -> String {
        self.node.path().to_string()
    }

    /// The node's 2.x session id: what 2.x nodes and tools know it by.
    #[getter]
    fn session_id(&self) -> i64 {
        self.node.compat_session_id()
    }

    /// The configuration the node runs in (`""` for none).
    #[getter]
    fn config(&self) -> String {
        self.node.config().to_string()
    }

    /// The channel `name`, relative to the node's namespace (or absolute
    /// with a leading `/`). Raises `ValueError` for a bad name.
    fn channel(&self, name: &str) -> PyResult<Channel> {
        let channel = self.node.try_channel(name).map_err(to_py)?;
        Ok(Channel::new(channel, &self.node))
    }

    /// A namespace below the node's (`..` goes up; a leading `/` starts at
    /// the root).
    fn ns(&self, path: &str) -> Namespace {
        Namespace::new(self.node.ns(path), &self.node)
    }

    /// Stops the node: its sockets close and its subscriptions end.
    fn stop(&self, py: Python<'_>) {
        py.detach(|| self.node.stop());
    }

    /// Whether the node has stopped.
    #[getter]
    fn stopped(&self) -> bool {
        self.node.is_stopped()
    }

    fn __enter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    #[pyo3(signature = (*_args))]
    fn __exit__(&self, py: Python<'_>, _args: &Bound<'_, pyo3::types::PyTuple>) {
        self.stop(py);
    }

    fn __repr__(&self) -> String {
        format!(
            "Node(name={:?}, namespace={:?})",
            self.node.name(),
            self.node.path()
        )
    }
}

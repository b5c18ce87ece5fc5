//! `Node`: a pulicast node, started when made.

use std::net::Ipv4Addr;
use std::time::Duration;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::channel::Namespace;
use crate::setting::FleetSettings;
use crate::to_py;

/// A pulicast node: `Node("rover_controller", namespace="rover1")`.
///
/// It starts when made (its sockets open, discovery begins) and runs on
/// threads of its own until `stop()`, the end of a `with` block, or the
/// end of the program (its callbacks are not called once the interpreter
/// exits). Channels are named as in Rust: relative to the
/// node's namespace, or absolute with a leading `/`.
#[pyclass(module = "pulicast_rs", frozen, extends = Namespace)]
pub(crate) struct Node {
    pub(crate) node: pulicast::Node,
}

#[pymethods]
impl Node {
    #[new]
    #[pyo3(signature = (name, namespace = "", *, port = None, interface = None, ttl = None, config = None, heartbeat_period = None, keys = None, keys_from_env = true, queue_capacity = None, receive_spin = None))]
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
        keys: Option<&str>,
        keys_from_env: bool,
        queue_capacity: Option<usize>,
        receive_spin: Option<f64>,
    ) -> PyResult<PyClassInitializer<Self>> {
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
        if let Some(keys) = keys {
            // The error names the entry, never the key.
            let keys = pulicast::parse_keys(keys)
                .map_err(|e| PyValueError::new_err(format!("keys: {e}")))?;
            for (namespace, key) in keys {
                builder = builder.key(namespace, key);
            }
        }
        if let Some(period) = heartbeat_period {
            builder = builder.heartbeat_period(crate::subscription::seconds(period)?);
        }
        if let Some(capacity) = queue_capacity {
            builder = builder.queue_capacity(capacity);
        }
        // No spin unless asked: a Python receiver's own work per message
        // is longer than the gaps a spin bridges, and where the scheduler
        // runs the answering process on the same CPU (it wakes it there),
        // a spin holds back the reply it waits for (docs/python.md, "Speed").
        let spin = receive_spin.map(crate::subscription::seconds).transpose()?;
        builder = builder.receive_spin(spin.unwrap_or(Duration::ZERO));
        let node = py.detach(|| builder.start_blocking()).map_err(to_py)?;
        // A node is its namespace too: channels, settings and services in
        // it come from `Namespace`'s methods.
        let ns = Namespace::new((*node).clone(), &node);
        Ok(PyClassInitializer::from(ns).add_subclass(Self { node }))
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

    /// The fleet's settings, read and changed as a tool does.
    fn fleet_settings(&self) -> FleetSettings {
        FleetSettings::new(&self.node)
    }

    /// The node's counters: what it received, delivered and sent, and what
    /// it dropped, by reason (`dropped`: reason -> count, the reasons as
    /// `puli-sniffer` names them).
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let stats = self.node.stats();
        let out = PyDict::new(py);
        out.set_item("datagrams_received", stats.datagrams_received)?;
        out.set_item("messages_received", stats.messages_received)?;
        out.set_item("messages_delivered", stats.messages_delivered)?;
        out.set_item("out_of_order_skipped", stats.out_of_order_skipped)?;
        out.set_item("messages_sent", stats.messages_sent)?;
        out.set_item("handler_panics", stats.handler_panics)?;
        out.set_item("late_answers", stats.late_answers)?;
        out.set_item("paced_datagrams", stats.paced_datagrams)?;
        out.set_item("paced_wait", stats.paced_wait.as_secs_f64())?;
        out.set_item("receive_sockets", stats.receive_sockets)?;
        let dropped = PyDict::new(py);
        for reason in pulicast::DropReason::ALL {
            dropped.set_item(reason.label(), stats.dropped(reason))?;
        }
        out.set_item("dropped", dropped)?;
        out.set_item("dropped_total", stats.dropped_total())?;
        Ok(out)
    }

    /// The fleet as discovery knows it: one dict per other member (this
    /// node too with `include_self=True`), with `name`, `namespace`,
    /// `config`, `host`, `key` (the 2.x session id), `address`,
    /// `data_address` (where its messages come from, if known), `state`
    /// (`alive`, `suspect`, `dead`, `left`), `compat` (a 2.x node), `site` (the
    /// site a bridge relays it from, else `None`), `publishes` and
    /// `subscribes` (channel names), and `periods` (channel name to its
    /// publishing period in seconds, where measured).
    #[pyo3(signature = (include_self = false))]
    fn members<'py>(
        &self,
        py: Python<'py>,
        include_self: bool,
    ) -> PyResult<Vec<Bound<'py, PyDict>>> {
        let members = py.detach(|| {
            let discovery = self.node.discovery();
            let mut members = discovery.members();
            if include_self {
                members.insert(0, discovery.local());
            }
            members
        });
        members
            .iter()
            .map(|m| crate::discovery::member_dict(py, m))
            .collect()
    }

    /// Fleet changes from now on: a `DiscoveryEvents` to receive from.
    fn discovery_events(&self) -> crate::discovery::DiscoveryEvents {
        crate::discovery::DiscoveryEvents::new(&self.node)
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

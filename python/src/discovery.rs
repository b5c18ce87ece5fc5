//! The fleet as discovery knows it: members as dicts, and the stream of
//! its changes.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pulicast::{DiscoveryEvent, MemberView};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// A member as a dict (see `Node.members`).
pub(crate) fn member_dict<'py>(py: Python<'py>, m: &MemberView) -> PyResult<Bound<'py, PyDict>> {
    let out = PyDict::new(py);
    out.set_item("name", &m.name)?;
    out.set_item("namespace", &m.namespace)?;
    out.set_item("config", &m.config)?;
    out.set_item("host", &m.host)?;
    out.set_item("key", m.key)?;
    out.set_item("address", m.address.to_string())?;
    out.set_item("data_address", m.data_address.map(|a| a.to_string()))?;
    out.set_item("state", format!("{:?}", m.state).to_lowercase())?;
    out.set_item("compat", m.compat)?;
    out.set_item("site", m.remote.as_ref().map(|r| r.site.clone()))?;
    let names = |publishes: bool| -> Vec<String> {
        m.channels
            .iter()
            .filter(|c| if publishes { c.publishes } else { c.subscribes })
            .map(|c| c.name.clone())
            .collect()
    };
    out.set_item("publishes", names(true))?;
    out.set_item("subscribes", names(false))?;
    let periods = PyDict::new(py);
    for c in m.channels.iter().filter(|c| c.publishes && c.period_ns > 0) {
        periods.set_item(&c.name, Duration::from_nanos(c.period_ns).as_secs_f64())?;
    }
    out.set_item("periods", periods)?;
    Ok(out)
}

/// One change of the fleet.
#[pyclass(module = "pulicast_rs", name = "DiscoveryEvent", frozen, get_all)]
pub(crate) struct DiscoveryEventView {
    /// `joined`, `left`, `failed`, `suspected`, `recovered`,
    /// `channel_appeared`, `channel_disappeared`, `suspicious` (or `other`,
    /// a kind newer than this package, described in `what`).
    kind: &'static str,
    /// The member's key (the 2.x session id).
    key: i64,
    /// The member's name (empty for `suspicious`).
    name: String,
    /// For `joined`: the member, as `Node.members` gives it.
    member: Option<Py<PyDict>>,
    /// For the channel events: the channel's name.
    channel: Option<String>,
    /// For the channel events: whether it publishes and subscribes it.
    publishes: Option<bool>,
    subscribes: Option<bool>,
    /// For `suspicious`: what happened.
    what: Option<String>,
}

impl DiscoveryEventView {
    fn new(py: Python<'_>, event: &DiscoveryEvent) -> PyResult<Self> {
        let plain = |kind, key: &i64, name: &String| Self {
            kind,
            key: *key,
            name: name.clone(),
            member: None,
            channel: None,
            publishes: None,
            subscribes: None,
            what: None,
        };
        Ok(match event {
            DiscoveryEvent::Joined(m) => Self {
                member: Some(member_dict(py, m)?.unbind()),
                ..plain("joined", &m.key, &m.name)
            },
            DiscoveryEvent::Left { key, name } => plain("left", key, name),
            DiscoveryEvent::Failed { key, name } => plain("failed", key, name),
            DiscoveryEvent::Suspected { key, name } => plain("suspected", key, name),
            DiscoveryEvent::Recovered { key, name } => plain("recovered", key, name),
            DiscoveryEvent::ChannelAppeared {
                key,
                member,
                channel,
            }
            | DiscoveryEvent::ChannelDisappeared {
                key,
                member,
                channel,
            } => Self {
                channel: Some(channel.name.clone()),
                publishes: Some(channel.publishes),
                subscribes: Some(channel.subscribes),
                ..plain(
                    if matches!(event, DiscoveryEvent::ChannelAppeared { .. }) {
                        "channel_appeared"
                    } else {
                        "channel_disappeared"
                    },
                    key,
                    member,
                )
            },
            DiscoveryEvent::Suspicious { key, what } => Self {
                what: Some(what.clone()),
                ..plain("suspicious", key, &String::new())
            },
            // A kind this package does not know yet: told, as what it is.
            other => Self {
                what: Some(format!("{other:?}")),
                ..plain("other", &0, &String::new())
            },
        })
    }
}

#[pymethods]
impl DiscoveryEventView {
    fn __repr__(&self) -> String {
        format!(
            "DiscoveryEvent({}, {:?}{})",
            self.kind,
            self.name,
            self.channel
                .as_ref()
                .map_or_else(String::new, |c| format!(", {c:?}"))
        )
    }
}

/// Fleet changes as they happen, from when it was made: `recv(timeout)`,
/// or iterate it (it ends when the node stops).
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct DiscoveryEvents {
    events: Arc<tokio::sync::Mutex<pulicast::DiscoveryEvents>>,
    /// What the stream missed, as of its last receive (read without
    /// waiting for a receive that holds the stream).
    missed: Arc<AtomicU64>,
    _node: pulicast::Node,
}

impl DiscoveryEvents {
    pub(crate) fn new(node: &pulicast::Node) -> Self {
        Self {
            events: Arc::new(tokio::sync::Mutex::new(node.discovery().events())),
            missed: Arc::new(AtomicU64::new(0)),
            _node: node.clone(),
        }
    }
}

impl DiscoveryEvents {
    /// The next change, within `timeout` (`None`: until one comes or the
    /// node stops).
    fn next(
        &self,
        timeout: Option<std::time::Duration>,
    ) -> impl std::future::Future<Output = Option<pulicast::DiscoveryEvent>> + Send + 'static {
        let (events, missed) = (Arc::clone(&self.events), Arc::clone(&self.missed));
        async move {
            // The lock inside the timeout: another thread's endless wait
            // holds the stream, and this one still ends in time.
            let next = async {
                let mut events = events.lock().await;
                let event = events.recv().await;
                missed.store(events.missed(), Ordering::Relaxed);
                event
            };
            match timeout {
                Some(t) => tokio::time::timeout(t, next).await.ok().flatten(),
                None => next.await,
            }
        }
    }
}

#[pymethods]
impl DiscoveryEvents {
    /// The next change, waiting up to `timeout` seconds (`None`: until one
    /// comes); `None` if none came in time or the node stopped. Ctrl-C
    /// interrupts the wait.
    #[pyo3(signature = (timeout = None))]
    fn recv(&self, py: Python<'_>, timeout: Option<f64>) -> PyResult<Option<DiscoveryEventView>> {
        let timeout = timeout.map(crate::subscription::seconds).transpose()?;
        let got = crate::wait(py, self.next(timeout))?;
        got.map(|e| DiscoveryEventView::new(py, &e)).transpose()
    }

    /// `recv` as an asyncio awaitable.
    #[pyo3(signature = (timeout = None))]
    fn recv_async<'py>(
        &self,
        py: Python<'py>,
        timeout: Option<f64>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let timeout = timeout.map(crate::bounded_seconds).transpose()?;
        let next = self.next(timeout);
        crate::awaitable(py, async move {
            let got = next.await;
            crate::attached(|py| got.map(|e| DiscoveryEventView::new(py, &e)).transpose())
        })
    }

    /// `async for event in events`: ends when the node stops.
    fn __aiter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    fn __anext__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let next = self.next(None);
        crate::awaitable(py, async move {
            let got = next.await;
            crate::attached(|py| got.map(|e| DiscoveryEventView::new(py, &e)).transpose())?
                .ok_or_else(|| pyo3::exceptions::PyStopAsyncIteration::new_err(()))
        })
    }

    /// Changes that came faster than they were taken and were dropped
    /// (the last thousand are kept), as of the last receive.
    #[getter]
    fn missed(&self) -> u64 {
        self.missed.load(Ordering::Relaxed)
    }

    fn __iter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    fn __next__(&self, py: Python<'_>) -> PyResult<Option<DiscoveryEventView>> {
        self.recv(py, None)
    }
}

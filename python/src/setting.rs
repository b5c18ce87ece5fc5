//! Settings: `Setting` (owned by this node) and `FleetSettings` (the
//! fleet's settings, read and changed as a tool does).

use pulicast::{Check, SettingInfo as Info};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyFloat, PyInt, PyString};

use crate::convert::{primitive_to_py, to_json, to_python};
use crate::to_py;

/// The owned setting, by its value's type.
enum Owned {
    Bool(pulicast::Setting<bool>),
    Int(pulicast::Setting<i64>),
    Float(pulicast::Setting<f64>),
    Str(pulicast::Setting<String>),
}

/// Runs `$body` with `$s` bound to the typed setting, whatever its type.
macro_rules! each {
    ($owned:expr, $s:ident => $body:expr) => {
        match $owned {
            Owned::Bool($s) => $body,
            Owned::Int($s) => $body,
            Owned::Float($s) => $body,
            Owned::Str($s) => $body,
        }
    };
}

/// What a setting of Python type `kind` is declared with.
struct Declared<'py> {
    initial: Bound<'py, PyAny>,
    range: Option<Bound<'py, PyAny>>,
    at_least: Option<Bound<'py, PyAny>>,
    at_most: Option<Bound<'py, PyAny>>,
    one_of: Option<Bound<'py, PyAny>>,
    read_only: bool,
    check: Option<Py<PyAny>>,
    unit: String,
    description: String,
}

/// A value Python hands us as a setting's type `T`, or `TypeError`
/// naming what was given.
trait FromPy: Sized {
    const NAME: &'static str;
    fn from_py(value: &Bound<'_, PyAny>) -> Option<Self>;
    fn to_py<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>>;
}

impl FromPy for bool {
    const NAME: &'static str = "a bool";
    fn from_py(value: &Bound<'_, PyAny>) -> Option<Self> {
        value.cast::<PyBool>().ok().map(|b| b.is_true())
    }
    fn to_py<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        Ok(PyBool::new(py, *self).to_owned().into_any())
    }
}

impl FromPy for i64 {
    const NAME: &'static str = "an int";
    fn from_py(value: &Bound<'_, PyAny>) -> Option<Self> {
        // bool is an int to Python, not to a setting.
        if value.is_instance_of::<PyBool>() || !value.is_instance_of::<PyInt>() {
            return None;
        }
        value.extract().ok()
    }
    fn to_py<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        Ok(self.into_pyobject(py)?.into_any())
    }
}

impl FromPy for f64 {
    const NAME: &'static str = "a float";
    fn from_py(value: &Bound<'_, PyAny>) -> Option<Self> {
        // An int is a float as Python's arithmetic sees it (1 for 1.0).
        if value.is_instance_of::<PyBool>() {
            return None;
        }
        if value.is_instance_of::<PyFloat>() || value.is_instance_of::<PyInt>() {
            return value.extract().ok();
        }
        None
    }
    fn to_py<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        Ok(PyFloat::new(py, *self).into_any())
    }
}

impl FromPy for String {
    const NAME: &'static str = "a str";
    fn from_py(value: &Bound<'_, PyAny>) -> Option<Self> {
        value.cast::<PyString>().ok().map(|s| s.to_string())
    }
    fn to_py<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        Ok(PyString::new(py, self).into_any())
    }
}

/// `value` as the setting's type, or `TypeError` saying what it is.
fn typed<T: FromPy>(what: &str, value: &Bound<'_, PyAny>) -> PyResult<T> {
    T::from_py(value).ok_or_else(|| {
        let given = value
            .get_type()
            .name()
            .map_or_else(|_| "?".to_string(), |n| n.to_string());
        PyTypeError::new_err(format!(
            "{what} must be {}, like the setting's initial value, not {given}",
            T::NAME
        ))
    })
}

impl<'py> Declared<'py> {
    /// The checks as pulicast takes them.
    fn checks<T: FromPy + pulicast::SettingValue>(&self) -> PyResult<Vec<Check<T>>> {
        let mut checks = Vec::new();
        if let Some(range) = &self.range {
            let pair: (Bound<'py, PyAny>, Bound<'py, PyAny>) = range.extract().map_err(|_| {
                PyTypeError::new_err("range must be a pair (lowest, highest), such as (0, 2)")
            })?;
            checks.push(Check::Range(
                typed("range's lowest", &pair.0)?,
                typed("range's highest", &pair.1)?,
            ));
        }
        if let Some(v) = &self.at_least {
            checks.push(Check::AtLeast(typed("at_least", v)?));
        }
        if let Some(v) = &self.at_most {
            checks.push(Check::AtMost(typed("at_most", v)?));
        }
        if let Some(values) = &self.one_of {
            let items = values
                .try_iter()
                .map_err(|_| PyTypeError::new_err("one_of must be a list of values"))?
                .map(|item| typed("each of one_of", &item?))
                .collect::<PyResult<Vec<T>>>()?;
            checks.push(Check::OneOf(items));
        }
        if self.read_only {
            checks.push(Check::ReadOnly);
        }
        if let Some(check) = &self.check {
            let check = check.clone_ref(self.initial.py());
            checks.push(Check::Custom(Box::new(move |v: &T| judge(&check, v))));
        }
        Ok(checks)
    }

    fn build<T: FromPy + pulicast::SettingValue>(
        &self,
        ns: &pulicast::Namespace,
        name: &str,
    ) -> PyResult<pulicast::Setting<T>> {
        let initial: T = typed("the initial value", &self.initial)?;
        let checks = self.checks::<T>()?;
        let mut builder = ns
            .setting_builder(name, initial)
            .unit(self.unit.clone())
            .describe(self.description.clone());
        for check in checks {
            builder = builder.check(check);
        }
        // Made without the GIL: the node's thread may run a Python check.
        self.initial
            .py()
            .detach(|| builder.build())
            .map_err(setting_error)
    }
}

/// What a Python check says of `value`: `None` or `True` accepts, a
/// string is the reason it refuses, `False` refuses; an exception refuses
/// with its text.
fn judge<T: FromPy>(check: &Py<PyAny>, value: &T) -> Result<(), String> {
    let mut verdict = Err("the program is exiting".to_string());
    crate::with_python(|py| {
        let said = value
            .to_py(py)
            .and_then(|v| check.call1(py, (v,)))
            .map(|r| r.into_bound(py));
        verdict = match said {
            Ok(r) if r.is_none() => Ok(()),
            Ok(r) => match r.cast::<PyBool>() {
                Ok(b) if b.is_true() => Ok(()),
                Ok(_) => Err("refused by the setting's check".to_string()),
                Err(_) => Err(r
                    .str()
                    .map_or_else(|_| "refused".to_string(), |s| s.to_string())),
            },
            Err(e) => Err(format!("the setting's check raised {e}")),
        };
    });
    verdict
}

/// A refused value as `ValueError`, other errors as usual.
fn setting_error(e: pulicast::Error) -> PyErr {
    match e {
        pulicast::Error::SettingRefused { .. } => PyValueError::new_err(e.to_string()),
        e => to_py(e),
    }
}

/// A distributed setting owned by this node: made by `Node.setting` and
/// `Namespace.setting`.
///
/// Any tool of the fleet (`puli config`, puliconf, `FleetSettings`) reads
/// it and asks it to change; every change, whoever asks, passes its
/// checks. Keep the object: the setting is withdrawn when it is dropped.
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct Setting {
    owned: Owned,
    /// Kept so the node runs while the setting is held.
    _node: pulicast::Node,
}

impl Setting {
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        ns: &pulicast::Namespace,
        node: &pulicast::Node,
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
    ) -> PyResult<Self> {
        if let Some(check) = &check {
            if !check.bind(initial.py()).is_callable() {
                return Err(PyTypeError::new_err(
                    "check must be callable: it is called with each value asked for",
                ));
            }
        }
        let declared = Declared {
            initial: initial.clone(),
            range,
            at_least,
            at_most,
            one_of,
            read_only,
            check,
            unit: unit.to_string(),
            description: description.to_string(),
        };
        let owned = if initial.is_instance_of::<PyBool>() {
            Owned::Bool(declared.build(ns, name)?)
        } else if initial.is_instance_of::<PyInt>() {
            Owned::Int(declared.build(ns, name)?)
        } else if initial.is_instance_of::<PyFloat>() {
            Owned::Float(declared.build(ns, name)?)
        } else if initial.is_instance_of::<PyString>() {
            Owned::Str(declared.build(ns, name)?)
        } else {
            let given = initial.get_type().name()?;
            return Err(PyTypeError::new_err(format!(
                "a setting's initial value is a bool, int, float or str, not {given}"
            )));
        };
        Ok(Self {
            owned,
            _node: node.clone(),
        })
    }
}

#[pymethods]
impl Setting {
    /// The fleet-wide name (`rover1/max_speed`).
    #[getter]
    fn name(&self) -> String {
        each!(&self.owned, s => s.name().to_string())
    }

    /// What tools are told of it: description, unit and checks.
    #[getter]
    fn about(&self, py: Python<'_>) -> String {
        py.detach(|| each!(&self.owned, s => s.about()))
    }

    /// The value; `None` once a tool unset it. Assigning sets it from
    /// this side (checked: `ValueError` if refused).
    #[getter]
    fn value<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        // Read without the GIL: a check may hold the setting's lock while
        // it waits for the GIL on the node's thread.
        each!(&self.owned, s => match py.detach(|| s.get()) {
            Some(v) => v.to_py(py),
            None => Ok(py.None().into_bound(py)),
        })
    }

    #[setter]
    fn set_value(&self, py: Python<'_>, value: &Bound<'_, PyAny>) -> PyResult<()> {
        self.set(py, value).map(|_| ())
    }

    /// Sets the value from this side, checked and confirmed to the fleet;
    /// `True` if it changed. `ValueError` if a check refuses it, `TypeError`
    /// if it is not of the setting's type.
    fn set(&self, py: Python<'_>, value: &Bound<'_, PyAny>) -> PyResult<bool> {
        each!(&self.owned, s => {
            let v = typed("the value", value)?;
            py.detach(|| s.set(v)).map_err(setting_error)
        })
    }

    /// Calls `callback(value)` after each change (a tool's or this
    /// side's), on the thread that made it. An exception in it is shown
    /// on stderr and changes nothing.
    fn on_change(&self, py: Python<'_>, callback: Py<PyAny>) -> PyResult<()> {
        if !callback.bind(py).is_callable() {
            return Err(PyTypeError::new_err(
                "on_change takes a callable: it is called with each new value",
            ));
        }
        let name = self.name();
        py.detach(|| {
            each!(&self.owned, s => s.on_change(move |v| {
                crate::with_python(|py| {
                    let called = match v {
                        Some(v) => v.to_py(py),
                        None => Ok(py.None().into_bound(py)),
                    }
                    .and_then(|v| callback.call1(py, (v,)));
                    if let Err(e) = called {
                        eprintln!("pulicast_rs: the on_change callback of setting {name} raised:");
                        e.display(py);
                    }
                });
            }))
        });
        Ok(())
    }

    fn __repr__(&self, py: Python<'_>) -> PyResult<String> {
        let value = self.value(py)?.repr()?.to_string();
        Ok(format!("Setting({:?}, value={value})", self.name()))
    }
}

/// A setting of the fleet, as its owner last confirmed it.
#[pyclass(module = "pulicast_rs", frozen, get_all)]
pub(crate) struct SettingInfo {
    /// The fleet-wide name (`rover1/max_speed`).
    name: String,
    /// The value (`None`: unset, or not confirmed yet).
    value: Py<PyAny>,
    /// The value as a person reads it (`"1.5"`, `"unset"`), if confirmed.
    text: Option<String>,
    /// Its type's name (`double_msg`), if confirmed.
    type_name: Option<String>,
    /// What its owner says it accepts (description, unit, checks).
    about: Option<String>,
    /// The owner's last message (a refusal or warning), empty if none.
    message: String,
    /// The nodes that own it (live ones).
    owners: Vec<String>,
    /// Two live owners answer for it: nobody should change it.
    locked: bool,
}

impl SettingInfo {
    fn new(py: Python<'_>, info: &Info) -> PyResult<Self> {
        let primitive = info.confirmed.as_ref().and_then(|c| c.value.as_ref());
        let value = match (primitive, info.value_json()) {
            (Some(p), _) => primitive_to_py(py, p)?.unbind(),
            (None, Some(v)) => to_python(py, &v)?.unbind(),
            (None, None) => py.None(),
        };
        Ok(Self {
            name: info.name.clone(),
            value,
            text: info.value_text(),
            type_name: info.type_name(),
            about: info.about.clone(),
            message: info
                .confirmed
                .as_ref()
                .map(|c| c.message.clone())
                .unwrap_or_default(),
            owners: info
                .owners
                .iter()
                .filter(|o| o.live)
                .map(|o| o.node.clone())
                .collect(),
            locked: info.is_locked(),
        })
    }
}

#[pymethods]
impl SettingInfo {
    fn __repr__(&self, py: Python<'_>) -> PyResult<String> {
        let value = self.value.bind(py).repr()?.to_string();
        Ok(format!(
            "SettingInfo({:?}, value={value}, owners={:?})",
            self.name, self.owners
        ))
    }
}

/// The fleet's settings, as a tool sees them: made by
/// `Node.fleet_settings()`.
///
/// Each method waits (the GIL released; Ctrl-C interrupts it) for
/// discovery to find the setting and its owner to answer, up to its
/// timeout; a refusal is `ValueError` with the owner's reason, a setting
/// not found in time `PulicastError`. Settings this node owns are not
/// listed (it holds their `Setting`).
#[pyclass(module = "pulicast_rs", frozen)]
pub(crate) struct FleetSettings {
    settings: std::sync::Arc<pulicast::FleetSettings>,
    /// Kept so the node runs while the client is used.
    _node: pulicast::Node,
}

impl FleetSettings {
    pub(crate) fn new(node: &pulicast::Node) -> Self {
        Self {
            settings: std::sync::Arc::new(node.fleet_settings()),
            _node: node.clone(),
        }
    }
}

/// A request to the fleet's settings: what its methods wait for here, or
/// hand to asyncio.
type Request = std::pin::Pin<Box<dyn std::future::Future<Output = pulicast::Result<Info>> + Send>>;

/// The requests that name a setting only.
#[derive(Clone, Copy)]
enum Ask {
    Get,
    Unset,
    Reset,
}

impl FleetSettings {
    fn named_request(&self, ask: Ask, name: &str, timeout: f64) -> PyResult<Request> {
        let timeout = crate::bounded_seconds(timeout)?;
        let (s, name) = (std::sync::Arc::clone(&self.settings), name.to_string());
        Ok(Box::pin(async move {
            match ask {
                Ask::Get => s.get(&name, timeout).await,
                Ask::Unset => s.unset(&name, timeout).await,
                Ask::Reset => s.reset(&name, timeout).await,
            }
        }))
    }

    fn set_request(&self, name: &str, value: &Bound<'_, PyAny>, timeout: f64) -> PyResult<Request> {
        let timeout = crate::bounded_seconds(timeout)?;
        let (s, name, value) = (
            std::sync::Arc::clone(&self.settings),
            name.to_string(),
            to_json(value)?,
        );
        Ok(Box::pin(
            async move { s.set_json(&name, value, timeout).await },
        ))
    }

    fn set_text_request(&self, name: &str, text: &str, timeout: f64) -> PyResult<Request> {
        let timeout = crate::bounded_seconds(timeout)?;
        let (s, name, text) = (
            std::sync::Arc::clone(&self.settings),
            name.to_string(),
            text.to_string(),
        );
        Ok(Box::pin(
            async move { s.set_text(&name, &text, timeout).await },
        ))
    }
}

/// Waits for `request` (the GIL released, Ctrl-C interrupts it).
fn answer(py: Python<'_>, request: Request) -> PyResult<SettingInfo> {
    let info = crate::wait(py, request)?.map_err(setting_error)?;
    SettingInfo::new(py, &info)
}

/// `request` as an asyncio awaitable.
fn answer_async(py: Python<'_>, request: Request) -> PyResult<Bound<'_, PyAny>> {
    crate::awaitable(py, async move {
        let info = request.await.map_err(setting_error)?;
        crate::attached(|py| SettingInfo::new(py, &info))
    })
}

#[pymethods]
impl FleetSettings {
    /// Every setting of the fleet: waits until each one found has answered
    /// (or was asked ten times) and none new appeared for `quiet` seconds.
    #[pyo3(signature = (quiet = 2.0))]
    fn list(&self, py: Python<'_>, quiet: f64) -> PyResult<Vec<SettingInfo>> {
        let quiet = crate::bounded_seconds(quiet)?;
        let settings = std::sync::Arc::clone(&self.settings);
        let found = crate::wait(py, async move { settings.list(quiet).await })?;
        found.iter().map(|i| SettingInfo::new(py, i)).collect()
    }

    /// `list` as an asyncio awaitable.
    #[pyo3(signature = (quiet = 2.0))]
    fn list_async<'py>(&self, py: Python<'py>, quiet: f64) -> PyResult<Bound<'py, PyAny>> {
        let quiet = crate::bounded_seconds(quiet)?;
        let settings = std::sync::Arc::clone(&self.settings);
        crate::awaitable(py, async move {
            let found = settings.list(quiet).await;
            crate::attached(|py| {
                found
                    .iter()
                    .map(|i| SettingInfo::new(py, i))
                    .collect::<PyResult<Vec<_>>>()
            })
        })
    }

    /// The setting `name` (`rover1/max_speed`) as its owner confirms it.
    #[pyo3(signature = (name, timeout = 3.0))]
    fn get(&self, py: Python<'_>, name: &str, timeout: f64) -> PyResult<SettingInfo> {
        answer(py, self.named_request(Ask::Get, name, timeout)?)
    }

    /// `get` as an asyncio awaitable.
    #[pyo3(signature = (name, timeout = 3.0))]
    fn get_async<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        timeout: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        answer_async(py, self.named_request(Ask::Get, name, timeout)?)
    }

    /// Asks the owner of `name` to take `value` (converted to the
    /// setting's type where nothing is lost) and returns the setting as
    /// confirmed.
    #[pyo3(signature = (name, value, timeout = 3.0))]
    fn set(
        &self,
        py: Python<'_>,
        name: &str,
        value: &Bound<'_, PyAny>,
        timeout: f64,
    ) -> PyResult<SettingInfo> {
        answer(py, self.set_request(name, value, timeout)?)
    }

    /// `set` as an asyncio awaitable.
    #[pyo3(signature = (name, value, timeout = 3.0))]
    fn set_async<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        value: &Bound<'_, PyAny>,
        timeout: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        answer_async(py, self.set_request(name, value, timeout)?)
    }

    /// Like `set`, with the value as a person types it (`"1.5"`, `"true"`).
    #[pyo3(signature = (name, text, timeout = 3.0))]
    fn set_text(
        &self,
        py: Python<'_>,
        name: &str,
        text: &str,
        timeout: f64,
    ) -> PyResult<SettingInfo> {
        answer(py, self.set_text_request(name, text, timeout)?)
    }

    /// `set_text` as an asyncio awaitable.
    #[pyo3(signature = (name, text, timeout = 3.0))]
    fn set_text_async<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        text: &str,
        timeout: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        answer_async(py, self.set_text_request(name, text, timeout)?)
    }

    /// Asks the owner of `name` to unset it (no value).
    #[pyo3(signature = (name, timeout = 3.0))]
    fn unset(&self, py: Python<'_>, name: &str, timeout: f64) -> PyResult<SettingInfo> {
        answer(py, self.named_request(Ask::Unset, name, timeout)?)
    }

    /// `unset` as an asyncio awaitable.
    #[pyo3(signature = (name, timeout = 3.0))]
    fn unset_async<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        timeout: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        answer_async(py, self.named_request(Ask::Unset, name, timeout)?)
    }

    /// Asks the owner of `name` to go back to its default.
    #[pyo3(signature = (name, timeout = 3.0))]
    fn reset(&self, py: Python<'_>, name: &str, timeout: f64) -> PyResult<SettingInfo> {
        answer(py, self.named_request(Ask::Reset, name, timeout)?)
    }

    /// `reset` as an asyncio awaitable.
    #[pyo3(signature = (name, timeout = 3.0))]
    fn reset_async<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        timeout: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        answer_async(py, self.named_request(Ask::Reset, name, timeout)?)
    }
}

//! Values between Python and pulicast's messages: what a Python value
//! is published as, and what a received payload becomes in Python.

use pyo3::exceptions::{PyOverflowError, PyTypeError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyByteArray, PyBytes, PyDict, PyFloat, PyInt, PyList, PyString};
use serde_json::Value;

/// What a Python value is published as.
pub(crate) enum Outgoing {
    /// A 2.x primitive message: `bool`, `int` (as `int64_msg`), `float`
    /// (as `double_msg`), `str`, as the 2.x package sends them.
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    /// `bytes`/`bytearray`: the payload as it is, no type.
    Raw(Vec<u8>),
}

/// The message `value` is published as; `TypeError` names what is not
/// supported yet.
pub(crate) fn outgoing(value: &Bound<'_, PyAny>) -> PyResult<Outgoing> {
    // `bool` first: it is an `int` to Python.
    if value.is_instance_of::<PyBool>() {
        return Ok(Outgoing::Bool(value.extract()?));
    }
    if value.is_instance_of::<PyInt>() {
        return value.extract::<i64>().map(Outgoing::Int).map_err(|_| {
            PyOverflowError::new_err(format!(
                "{value} does not fit a 64-bit signed integer (int64_msg)"
            ))
        });
    }
    if value.is_instance_of::<PyFloat>() {
        return Ok(Outgoing::Float(value.extract()?));
    }
    if value.is_instance_of::<PyString>() {
        return Ok(Outgoing::Str(value.extract()?));
    }
    if let Ok(bytes) = value.cast::<PyBytes>() {
        return Ok(Outgoing::Raw(bytes.as_bytes().to_vec()));
    }
    if let Ok(bytes) = value.cast::<PyByteArray>() {
        return Ok(Outgoing::Raw(bytes.to_vec()));
    }
    let type_name = value
        .get_type()
        .name()
        .map_or_else(|_| "?".to_string(), |n| n.to_string());
    Err(PyTypeError::new_err(format!(
        "can't publish a {type_name}: publish bool, int, float, str, bytes or bytearray"
    )))
}

/// A JSON value (a decoded message) as Python: objects as dicts, arrays
/// as lists.
pub(crate) fn to_python<'py>(py: Python<'py>, value: &Value) -> PyResult<Bound<'py, PyAny>> {
    Ok(match value {
        Value::Null => py.None().into_bound(py),
        Value::Bool(b) => PyBool::new(py, *b).to_owned().into_any(),
        Value::Number(n) => match (n.as_i64(), n.as_u64(), n.as_f64()) {
            (Some(i), _, _) => i.into_pyobject(py)?.into_any(),
            (None, Some(u), _) => u.into_pyobject(py)?.into_any(),
            (None, None, Some(f)) => f.into_pyobject(py)?.into_any(),
            (None, None, None) => py.None().into_bound(py),
        },
        Value::String(s) => PyString::new(py, s).into_any(),
        Value::Array(items) => {
            let list = PyList::empty(py);
            for item in items {
                list.append(to_python(py, item)?)?;
            }
            list.into_any()
        }
        Value::Object(fields) => {
            let dict = PyDict::new(py);
            for (key, item) in fields {
                dict.set_item(key, to_python(py, item)?)?;
            }
            dict.into_any()
        }
    })
}

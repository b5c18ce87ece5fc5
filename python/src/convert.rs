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

/// The bytes of a bytes-like object (`bytes`, `bytearray`, `memoryview`).
pub(crate) fn bytes_of(value: &Bound<'_, PyAny>) -> PyResult<Vec<u8>> {
    if let Ok(bytes) = value.cast::<PyBytes>() {
        return Ok(bytes.as_bytes().to_vec());
    }
    if let Ok(bytes) = value.cast::<PyByteArray>() {
        return Ok(bytes.to_vec());
    }
    // A memoryview (or anything else of the buffer protocol), through bytes().
    let converted = value
        .py()
        .get_type::<PyBytes>()
        .call1((value,))
        .map_err(|_| PyTypeError::new_err("expected bytes, bytearray or memoryview"))?;
    Ok(converted.cast::<PyBytes>()?.as_bytes().to_vec())
}

/// The payload `value` is published as: a 2.x primitive message
/// (fingerprint and value) or the bytes as they are.
pub(crate) fn payload(value: &Outgoing) -> Vec<u8> {
    let primitive = match value {
        Outgoing::Bool(b) => pulicast::Primitive::Bool(*b),
        Outgoing::Int(i) => pulicast::Primitive::I64(*i),
        Outgoing::Float(f) => pulicast::Primitive::Double(*f),
        Outgoing::Str(s) => pulicast::Primitive::String(s.clone()),
        Outgoing::Raw(bytes) => return bytes.clone(),
    };
    let mut out = Vec::new();
    primitive.encode(&mut out);
    out
}

/// `encode(value)`: the payload `Channel.publish(value)` sends, as
/// `bytes` (for the 2.x layer, which sends ZCM classes' own encodings
/// beside these).
#[pyfunction]
pub(crate) fn encode<'py>(
    py: Python<'py>,
    value: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyBytes>> {
    Ok(PyBytes::new(py, &payload(&outgoing(value)?)))
}

/// `decode(payload)`: `(type_name, value)` of a payload read without an
/// announced type: 2.x primitives as their value, anything else as
/// `("bytes", payload)`.
#[pyfunction]
pub(crate) fn decode<'py>(
    py: Python<'py>,
    payload: &[u8],
) -> PyResult<(String, Bound<'py, PyAny>)> {
    read(py, payload, None)
}

/// A payload as Python: a 2.x primitive as its value (a float stays a
/// float, NaN and infinities included), a native type its channel
/// announces (`hint`) as dicts and lists, anything else as `bytes`.
pub(crate) fn read<'py>(
    py: Python<'py>,
    payload: &[u8],
    hint: Option<&pulicast::TypeInfo>,
) -> PyResult<(String, Bound<'py, PyAny>)> {
    use pulicast::Primitive as P;
    if let Ok(primitive) = P::decode(payload) {
        let name = primitive.kind().type_name().to_string();
        let value = match primitive {
            P::Bool(b) => PyBool::new(py, b).to_owned().into_any(),
            P::Byte(v) => v.into_pyobject(py)?.into_any(),
            P::I8(v) => v.into_pyobject(py)?.into_any(),
            P::I16(v) => v.into_pyobject(py)?.into_any(),
            P::I32(v) => v.into_pyobject(py)?.into_any(),
            P::I64(v) => v.into_pyobject(py)?.into_any(),
            P::Float(v) | P::Double(v) => v.into_pyobject(py)?.into_any(),
            P::String(s) => PyString::new(py, &s).into_any(),
        };
        return Ok((name, value));
    }
    let decoded = pulicast::text::decode_payload(payload, hint);
    let value = match decoded.type_name.as_str() {
        "bytes" => PyBytes::new(py, payload).into_any(),
        _ => to_python(py, &decoded.value)?,
    };
    Ok((decoded.type_name, value))
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

//! Values between Python and pulicast's messages: what a Python value
//! is published as, and what a received payload becomes in Python.

use pyo3::exceptions::{PyOverflowError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{
    PyBool, PyByteArray, PyBytes, PyDict, PyFloat, PyInt, PyList, PyMemoryView, PyString, PyTuple,
};
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
    // A memoryview, through bytes(); nothing else (bytes(5) is five zeros,
    // bytes([1, 2]) a list's: neither is what was meant).
    if !value.is_instance_of::<PyMemoryView>() {
        return Err(PyTypeError::new_err(
            "expected bytes, bytearray or memoryview",
        ));
    }
    let converted = value.py().get_type::<PyBytes>().call1((value,))?;
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
/// announces (`known`) as dicts and lists, anything else as `bytes`.
pub(crate) fn read<'py>(
    py: Python<'py>,
    payload: &[u8],
    known: Option<&Known>,
) -> PyResult<(String, Bound<'py, PyAny>)> {
    if let Ok(primitive) = pulicast::Primitive::decode(payload) {
        let name = primitive.kind().type_name().to_string();
        let value = primitive_to_py(py, &primitive)?;
        return Ok((name, value));
    }
    let hint = known.and_then(|k| Some((&k.info, k.schema.as_ref()?)));
    match pulicast::text::decode_typed(payload, hint) {
        Some(decoded) => Ok((decoded.type_name, to_python(py, &decoded.value)?)),
        None => Ok(("bytes".to_string(), PyBytes::new(py, payload).into_any())),
    }
}

/// A type a channel's members announce, its description parsed once for
/// all the messages read by it.
pub(crate) struct Known {
    pub(crate) info: pulicast::TypeInfo,
    pub(crate) schema: Option<pulicast::postcard_schema::schema::owned::OwnedNamedType>,
}

impl Known {
    pub(crate) fn new(info: pulicast::TypeInfo) -> Self {
        let schema = match info.encoding {
            pulicast::TypeEncoding::Native => pulicast::text::schema_of(&info),
            pulicast::TypeEncoding::Zcm => None,
        };
        Self { info, schema }
    }
}

/// A 2.x primitive as Python (a NaN stays a float).
pub(crate) fn primitive_to_py<'py>(
    py: Python<'py>,
    p: &pulicast::Primitive,
) -> PyResult<Bound<'py, PyAny>> {
    Ok(match p {
        pulicast::Primitive::Bool(v) => PyBool::new(py, *v).to_owned().into_any(),
        pulicast::Primitive::Byte(v) => v.into_pyobject(py)?.into_any(),
        pulicast::Primitive::I8(v) => v.into_pyobject(py)?.into_any(),
        pulicast::Primitive::I16(v) => v.into_pyobject(py)?.into_any(),
        pulicast::Primitive::I32(v) => v.into_pyobject(py)?.into_any(),
        pulicast::Primitive::I64(v) => v.into_pyobject(py)?.into_any(),
        pulicast::Primitive::Float(v) | pulicast::Primitive::Double(v) => {
            PyFloat::new(py, *v).into_any()
        }
        pulicast::Primitive::String(v) => PyString::new(py, v).into_any(),
    })
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

/// A Python value as JSON: `bool`, `int`, `float`, `str`, `None`, and
/// lists and dicts of them.
pub(crate) fn to_json(value: &Bound<'_, PyAny>) -> PyResult<Value> {
    json_of(value, 0)
}

/// How deep lists and dicts nest in a value, at most: a list that holds
/// itself is refused, not followed until the stack overflows.
const MAX_DEPTH: usize = 64;

fn json_of(value: &Bound<'_, PyAny>, depth: usize) -> PyResult<Value> {
    if depth > MAX_DEPTH {
        return Err(PyValueError::new_err(format!(
            "a value nests deeper than {MAX_DEPTH} lists and dicts (or holds itself)"
        )));
    }
    if value.is_none() {
        return Ok(Value::Null);
    }
    if let Ok(b) = value.cast::<PyBool>() {
        return Ok(Value::Bool(b.is_true()));
    }
    if value.is_instance_of::<PyInt>() {
        if let Ok(i) = value.extract::<i64>() {
            return Ok(Value::from(i));
        }
        return value
            .extract::<u64>()
            .map(Value::from)
            .map_err(|_| PyValueError::new_err(format!("{value} is too large for 64 bits")));
    }
    if let Ok(f) = value.cast::<PyFloat>() {
        let f = f.value();
        return serde_json::Number::from_f64(f)
            .map(Value::Number)
            .ok_or_else(|| PyValueError::new_err(format!("{f} is not a number JSON can carry")));
    }
    if let Ok(s) = value.cast::<PyString>() {
        return Ok(Value::String(s.to_string()));
    }
    if value.is_instance_of::<PyList>() || value.is_instance_of::<PyTuple>() {
        let items = value
            .try_iter()?
            .map(|item| json_of(&item?, depth + 1))
            .collect::<PyResult<Vec<_>>>()?;
        return Ok(Value::Array(items));
    }
    if let Ok(dict) = value.cast::<PyDict>() {
        let mut fields = serde_json::Map::new();
        for (key, item) in dict.iter() {
            let key = key.cast::<PyString>().map_err(|_| {
                PyTypeError::new_err(format!("a dict's keys must be str, not {key:?}"))
            })?;
            fields.insert(key.to_string(), json_of(&item, depth + 1)?);
        }
        return Ok(Value::Object(fields));
    }
    let given = value.get_type().name()?;
    Err(PyTypeError::new_err(format!(
        "a value is a bool, int, float, str, None, or a list or dict of them, not {given}"
    )))
}

/// `value` as a 2.x primitive of `kind`: a `bool` for `boolean_msg`, an
/// `int` that fits for the integers, an `int` or `float` for the floats, a
/// `str` for `string_msg`; `TypeError` or `OverflowError` otherwise.
fn primitive_of(
    value: &Bound<'_, PyAny>,
    kind: pulicast::PrimitiveKind,
) -> PyResult<pulicast::Primitive> {
    use pulicast::{Primitive as P, PrimitiveKind as K};
    let wrong = || {
        let given = value
            .get_type()
            .name()
            .map_or_else(|_| "?".to_string(), |n| n.to_string());
        PyTypeError::new_err(format!(
            "expected a value for {}, not {given}",
            kind.type_name()
        ))
    };
    let is_bool = value.is_instance_of::<PyBool>();
    let is_int = value.is_instance_of::<PyInt>() && !is_bool;
    let int = || -> PyResult<i64> {
        if !is_int {
            return Err(wrong());
        }
        value.extract::<i64>().map_err(|_| {
            PyOverflowError::new_err(format!("{value} does not fit {}", kind.type_name()))
        })
    };
    let fits = |v: i64, ok: bool| {
        if ok {
            Ok(v)
        } else {
            Err(PyOverflowError::new_err(format!(
                "{v} does not fit {}",
                kind.type_name()
            )))
        }
    };
    Ok(match kind {
        K::Bool if is_bool => P::Bool(value.extract()?),
        K::Bool => return Err(wrong()),
        K::Byte => {
            let v = int()?;
            P::Byte(fits(v, u8::try_from(v).is_ok())? as u8)
        }
        K::I8 => {
            let v = int()?;
            P::I8(fits(v, i8::try_from(v).is_ok())? as i8)
        }
        K::I16 => {
            let v = int()?;
            P::I16(fits(v, i16::try_from(v).is_ok())? as i16)
        }
        K::I32 => {
            let v = int()?;
            P::I32(fits(v, i32::try_from(v).is_ok())? as i32)
        }
        K::I64 => P::I64(int()?),
        K::Float | K::Double if is_int || value.is_instance_of::<PyFloat>() => {
            let v: f64 = value.extract()?;
            if kind == K::Float {
                P::Float(v)
            } else {
                P::Double(v)
            }
        }
        K::Float | K::Double => return Err(wrong()),
        K::String => P::String(value.cast::<PyString>().map_err(|_| wrong())?.to_string()),
    })
}

/// `value` encoded as a message of type `ty` (fingerprint first), as a
/// server or caller announces it: a 2.x primitive of its kind, a native
/// type from dicts and lists (a `ValueError` names the field that does not
/// fit), `bytes` for no type.
pub(crate) fn encode_as(
    value: &Bound<'_, PyAny>,
    ty: Option<&pulicast::TypeInfo>,
) -> PyResult<Vec<u8>> {
    let Some(ty) = ty else {
        return bytes_of(value)
            .map_err(|_| PyTypeError::new_err("its type is raw bytes: give bytes or bytearray"));
    };
    if let Some(kind) =
        pulicast::PrimitiveKind::from_fingerprint(pulicast::Fingerprint(ty.fingerprint))
    {
        let mut out = Vec::new();
        primitive_of(value, kind)?.encode(&mut out);
        return Ok(out);
    }
    let schema = match ty.encoding {
        pulicast::TypeEncoding::Native => pulicast::text::schema_of(ty),
        pulicast::TypeEncoding::Zcm => None,
    };
    let Some(schema) = schema else {
        return Err(PyTypeError::new_err(format!(
            "{} is announced without a description to write it from",
            ty.name
        )));
    };
    pulicast::text::encode_native_value(&schema, ty.fingerprint, &to_json(value)?)
        .map_err(|e| PyValueError::new_err(format!("not a {}: {}: {}", ty.name, e.path, e.problem)))
}

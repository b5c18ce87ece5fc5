"""Messages as Pulicast 2.x programs send and receive them.

The 2.x rules, kept for programs that move to `pulicast_rs` by their import
line:

- What is sent is chosen by the value's exact type: `int` as `int64_msg`,
  `float` as `double_msg`, `bool`, `str`, `bytes` as they are, `None` as an
  empty payload, an instance of a registered ZCM class by its own
  `encode()`. Any other type raises `KeyError`.
- What a callback receives is chosen by the annotation of its message
  parameter: `int`, `float`, `bool` or `str` take the 2.x primitive messages
  whose value is exactly that type; `bytes` takes the payload as it came (a
  `bytearray`); a registered ZCM class takes what its `decode` reads; no
  annotation (or `Any`) takes primitives as their value and registered ZCM
  classes as objects, and drops anything else.

ZCM classes are the ones `zcm-gen` makes for Python: `encode()`, a static
`decode(data)` and a static `_get_packed_fingerprint()`. Register them with
`register_zcm_type` or a whole package with `register_zcm_package`. If the
2.x package `pulicast_messages` is installed, its classes are registered
at import, as 2.x does.
"""

import inspect
import logging
from typing import Any, Callable, Dict, Optional

from . import _native

# The 2.x primitive messages, by name, and the Python type of their value.
PRIMITIVE_MESSAGES = {
    "boolean_msg": bool,
    "byte_msg": int,
    "int8_msg": int,
    "int16_msg": int,
    "int32_msg": int,
    "int64_msg": int,
    "float_msg": float,
    "double_msg": float,
    "string_msg": str,
}

primitive_types = (int, float, bool, str)

# Registered ZCM classes by their packed fingerprint (the payload's first
# 8 bytes); a later registration of a fingerprint wins, as in 2.x.
zcm_message_types_by_fingerprint: Dict[bytes, type] = {}

# Every class registered: one whose fingerprint another took over is still
# sent and received by its own type, as in 2.x.
_registered_types = set()

_log = logging.getLogger("pulicast_rs")


def is_zcm_type(t) -> bool:
    """Whether `t` looks like a ZCM-generated class."""
    return all(hasattr(t, a) for a in ("encode", "decode", "_get_packed_fingerprint"))


def register_zcm_type(t: type) -> None:
    """Registers the ZCM class `t`: it can be sent with `<<` and received by
    annotating a callback's message parameter with it (or with nothing)."""
    if not is_zcm_type(t):
        raise TypeError(f"{t!r} is no ZCM class (encode, decode, _get_packed_fingerprint)")
    zcm_message_types_by_fingerprint[bytes(t._get_packed_fingerprint())] = t
    _registered_types.add(t)


def register_zcm_package(package) -> None:
    """Registers every ZCM class of a module or package."""
    for _, member in inspect.getmembers(package):
        if inspect.isclass(member) and is_zcm_type(member):
            register_zcm_type(member)


def _registered(t) -> bool:
    return inspect.isclass(t) and t in _registered_types


def get_message_encoder(t) -> Callable[[Any], bytes]:
    """The encoder of values of exactly type `t`; `KeyError` if none."""
    if t in (int, float, bool, str):
        return _native.encode
    if t is bytes:
        return bytes
    if t is type(None):
        return lambda _: b""
    if _registered(t):
        return lambda message: bytes(message.encode())
    raise KeyError(f"no encoder for {t!r}: send int, float, bool, str, bytes, None or a registered ZCM class")


def encode(message) -> bytes:
    """The payload `message` is sent as (by its exact type)."""
    return get_message_encoder(type(message))(message)


def _decode_any(payload: bytes) -> Optional[Any]:
    name, value = _native.decode(payload)
    if name in PRIMITIVE_MESSAGES:
        return value
    cls = zcm_message_types_by_fingerprint.get(bytes(payload[:8]))
    if cls is None:
        return None
    return _decode_zcm(cls, payload)


def _decode_zcm(cls, payload: bytes) -> Optional[Any]:
    try:
        return cls.decode(payload)
    except ValueError as e:
        # The generated code says a fingerprint that is not its own so.
        if "Decode error" in e.args:
            return None
        raise


def get_message_decoder(t) -> Callable[[bytes], Optional[Any]]:
    """The decoder for messages of type `t` (a payload to a value, or None
    when the payload is not one); `KeyError` if `t` can't be received."""
    if t is Any:
        return _decode_any
    if t is bytes:
        return bytearray
    if t in primitive_types:

        def primitive(payload: bytes):
            name, value = _native.decode(payload)
            # Exactly the type: an int subscriber gets no bool.
            if name in PRIMITIVE_MESSAGES and type(value) is t:
                return value
            return None

        return primitive
    if _registered(t):
        return lambda payload: _decode_zcm(t, payload)
    raise KeyError(t)


try:  # The 2.x package's own message classes, if installed, as 2.x registers them.
    import pulicast_messages as _pulicast_messages  # type: ignore

    register_zcm_package(_pulicast_messages)
except ImportError:
    pass

"""Type stubs of the native module (python/src/*.rs)."""

from types import TracebackType
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple, Type, Union

DEFAULT_PORT: int

class PulicastError(Exception):
    """An error of the pulicast node: a stopped node, a socket that failed."""

class Message:
    """One received message."""

    @property
    def value(self) -> Any:
        """bool/int/float/str for 2.x primitives; dict/list for a native type
        its channel announces; bytes for anything else."""
    @property
    def type_name(self) -> str: ...
    @property
    def source(self) -> str:
        """The sender's address, "ip:port"."""
    @property
    def lead(self) -> int: ...
    @property
    def seq(self) -> int: ...
    @property
    def channel(self) -> str: ...
    @property
    def payload(self) -> bytes:
        """The payload as it came (a typed message's fingerprint first)."""

class Subscription:
    """Receive with recv(timeout) or by iterating; close() unsubscribes."""

    @property
    def channel(self) -> str: ...
    def recv(self, timeout: Optional[float] = None) -> Optional[Message]: ...
    def recv_many(self, max: int, timeout: Optional[float] = None) -> List[Message]: ...
    def close(self) -> None: ...
    def __iter__(self) -> Iterator[Message]: ...
    def __next__(self) -> Message: ...
    def __enter__(self) -> "Subscription": ...
    def __exit__(
        self,
        exc_type: Optional[Type[BaseException]],
        exc: Optional[BaseException],
        tb: Optional[TracebackType],
    ) -> None: ...

class CallbackSubscription:
    """A callback called on the node's receive thread; close() unsubscribes."""

    @property
    def channel(self) -> str: ...
    @property
    def errors(self) -> int:
        """How many times the callback raised."""
    def close(self) -> None: ...
    def __enter__(self) -> "CallbackSubscription": ...
    def __exit__(
        self,
        exc_type: Optional[Type[BaseException]],
        exc: Optional[BaseException],
        tb: Optional[TracebackType],
    ) -> None: ...

Publishable = Union[bool, int, float, str, bytes, bytearray]

class Channel:
    @property
    def name(self) -> str: ...
    def publish(self, value: Publishable) -> None: ...
    def publish_bytes(self, payload: Union[bytes, bytearray, memoryview]) -> None: ...
    def subscribe(
        self, callback: Optional[Callable[[Message], Any]] = None
    ) -> Union[Subscription, CallbackSubscription]: ...
    def publishers(self) -> List[str]: ...

class Namespace:
    @property
    def path(self) -> str: ...
    def channel(self, name: str) -> Channel: ...
    def ns(self, path: str) -> "Namespace": ...

class Node:
    def __init__(
        self,
        name: str,
        namespace: str = "",
        *,
        port: Optional[int] = None,
        interface: Optional[str] = None,
        ttl: Optional[int] = None,
        config: Optional[str] = None,
        heartbeat_period: Optional[float] = None,
        keys: Optional[str] = None,
        keys_from_env: bool = True,
    ) -> None: ...
    @property
    def session_id(self) -> int:
        """The 2.x session id."""
    @property
    def name(self) -> str: ...
    @property
    def namespace(self) -> str: ...
    @property
    def config(self) -> str: ...
    @property
    def stopped(self) -> bool: ...
    def channel(self, name: str) -> Channel: ...
    def ns(self, path: str) -> Namespace: ...
    def stats(self) -> Dict[str, Any]:
        """Counters; "dropped" maps each drop reason to its count."""
    def members(self) -> List[Dict[str, Any]]:
        """The other members of the fleet, as discovery knows them."""
    def stop(self) -> None: ...
    def __enter__(self) -> "Node": ...
    def __exit__(
        self,
        exc_type: Optional[Type[BaseException]],
        exc: Optional[BaseException],
        tb: Optional[TracebackType],
    ) -> None: ...

def encode(value: Publishable) -> bytes:
    """The payload Channel.publish(value) sends."""

def decode(payload: bytes) -> Tuple[str, Any]:
    """(type_name, value) of a payload read without an announced type."""

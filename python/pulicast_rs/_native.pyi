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
    async def recv_async(self, timeout: Optional[float] = None) -> Optional[Message]: ...
    def __aiter__(self) -> "Subscription": ...
    async def __anext__(self) -> Message: ...
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
    """A callback called on a thread of the subscription; close() unsubscribes."""

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
    def subscribers(self) -> List[str]: ...
    def wait_for_publisher(self, timeout: float) -> str: ...
    def enable_batching(self, max_delay: float) -> None: ...
    def disable_batching(self) -> None: ...
    def flush(self) -> None: ...

SettingValue = Union[bool, int, float, str]

class Setting:
    """A setting this node owns; any tool of the fleet reads and changes it."""

    @property
    def name(self) -> str:
        """The fleet-wide name ("rover1/max_speed")."""
    @property
    def about(self) -> str:
        """Description, unit and checks, as tools show them."""
    @property
    def value(self) -> Optional[SettingValue]:
        """None once a tool unset it. Assign to set it (ValueError if refused)."""
    @value.setter
    def value(self, value: SettingValue) -> None: ...
    def set(self, value: SettingValue) -> bool:
        """Sets it from this side, checked; True if it changed."""
    def on_change(self, callback: Callable[[Optional[SettingValue]], Any]) -> None:
        """callback(new_value) after each change, on the thread that made it."""

class SettingInfo:
    """A setting of the fleet, as its owner last confirmed it."""

    name: str
    value: Any
    text: Optional[str]
    type_name: Optional[str]
    about: Optional[str]
    message: str
    owners: List[str]
    locked: bool

class FleetSettings:
    """The fleet's settings, read and changed as a tool does (blocking)."""

    def list(self, quiet: float = 2.0) -> List[SettingInfo]: ...
    def get(self, name: str, timeout: float = 3.0) -> SettingInfo: ...
    def set(self, name: str, value: Any, timeout: float = 3.0) -> SettingInfo: ...
    def set_text(self, name: str, text: str, timeout: float = 3.0) -> SettingInfo: ...
    def unset(self, name: str, timeout: float = 3.0) -> SettingInfo: ...
    def reset(self, name: str, timeout: float = 3.0) -> SettingInfo: ...
    async def list_async(self, quiet: float = 2.0) -> List[SettingInfo]: ...
    async def get_async(self, name: str, timeout: float = 3.0) -> SettingInfo: ...
    async def set_async(self, name: str, value: Any, timeout: float = 3.0) -> SettingInfo: ...
    async def set_text_async(self, name: str, text: str, timeout: float = 3.0) -> SettingInfo: ...
    async def unset_async(self, name: str, timeout: float = 3.0) -> SettingInfo: ...
    async def reset_async(self, name: str, timeout: float = 3.0) -> SettingInfo: ...

ServiceValue = Union[bool, int, float, str, bytes]

class Server:
    """A service this node serves; close() (or dropping it) stops serving."""

    @property
    def service(self) -> str: ...
    @property
    def running(self) -> int: ...
    def close(self) -> None: ...
    def __enter__(self) -> "Server": ...
    def __exit__(
        self,
        exc_type: Optional[Type[BaseException]],
        exc: Optional[BaseException],
        tb: Optional[TracebackType],
    ) -> None: ...

class Call:
    """The call a handler of two arguments runs."""

    @property
    def cancelled(self) -> bool: ...
    @property
    def caller(self) -> Optional[str]: ...
    @property
    def time_left(self) -> Optional[float]: ...
    def progress(self, value: Any) -> None: ...

class OngoingCall:
    """A call in flight: iterate it for progress, then reply()."""

    @property
    def node(self) -> str: ...
    def progress(self) -> Optional[Any]: ...
    def reply(self) -> Any: ...
    async def progress_async(self) -> Optional[Any]: ...
    async def reply_async(self) -> Any: ...
    def cancel(self) -> None: ...
    def __iter__(self) -> Iterator[Any]: ...
    def __next__(self) -> Any: ...
    def __aiter__(self) -> "OngoingCall": ...
    async def __anext__(self) -> Any: ...

class Serving:
    """What `serve(name)` without a handler returns: a decorator."""

    def __call__(self, handler: Callable[..., Any]) -> Server: ...

class Client:
    """A client of a service; requests in the types its server announces."""

    @property
    def service(self) -> str: ...
    def servers(self) -> List[str]: ...
    def nearest(self) -> "Client": ...
    def call(self, request: Any, timeout: Optional[float] = None) -> Any: ...
    async def call_async(self, request: Any, timeout: Optional[float] = None) -> Any: ...
    def start(self, request: Any, timeout: Optional[float] = None) -> OngoingCall: ...
    def call_all(
        self, request: Any, timeout: Optional[float] = None
    ) -> List[Tuple[str, Any, Optional[str]]]: ...

class DiscoveryEvent:
    """One change of the fleet."""

    kind: str
    key: int
    name: str
    member: Optional[Dict[str, Any]]
    channel: Optional[str]
    publishes: Optional[bool]
    subscribes: Optional[bool]
    what: Optional[str]

class DiscoveryEvents:
    """Fleet changes from when it was made: recv(timeout), or iterate it."""

    def recv(self, timeout: Optional[float] = None) -> Optional[DiscoveryEvent]: ...
    @property
    def missed(self) -> int: ...
    def __iter__(self) -> Iterator[DiscoveryEvent]: ...
    def __next__(self) -> DiscoveryEvent: ...
    async def recv_async(self, timeout: Optional[float] = None) -> Optional[DiscoveryEvent]: ...
    def __aiter__(self) -> "DiscoveryEvents": ...
    async def __anext__(self) -> DiscoveryEvent: ...

class Namespace:
    @property
    def path(self) -> str: ...
    def channel(self, name: str) -> Channel: ...
    def ns(self, path: str) -> "Namespace": ...
    def setting(
        self,
        name: str,
        initial: SettingValue,
        *,
        range: Optional[Tuple[SettingValue, SettingValue]] = None,
        at_least: Optional[SettingValue] = None,
        at_most: Optional[SettingValue] = None,
        one_of: Optional[List[SettingValue]] = None,
        read_only: bool = False,
        check: Optional[Callable[[SettingValue], Union[None, bool, str]]] = None,
        unit: str = "",
        description: str = "",
    ) -> Setting:
        """A setting owned by this node, of initial's type."""
    def serve(
        self,
        name: str,
        handler: Optional[Callable[..., Any]] = None,
        *,
        request: Optional[type] = None,
        reply: Optional[type] = None,
        progress: Optional[type] = None,
        concurrency: Optional[int] = None,
    ) -> Any:
        """A Server for handler; without one, a decorator that makes it."""
    def client(self, name: str, *, timeout: float = 5.0) -> Client: ...

class Node(Namespace):
    """A node: its own namespace too (channel, ns, setting, serve, client)."""

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
        queue_capacity: Optional[int] = None,
        receive_spin: Optional[float] = None,
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
    def fleet_settings(self) -> FleetSettings: ...
    def stats(self) -> Dict[str, Any]:
        """Counters; "dropped" maps each drop reason to its count."""
    def members(self, include_self: bool = False) -> List[Dict[str, Any]]:
        """The members of the fleet, as discovery knows them."""
    def discovery_events(self) -> DiscoveryEvents: ...
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

"""`ThreadedNode`: the Pulicast 2.x node API on pulicast-rs, so that a 2.x
program runs by changing its import line to `import pulicast_rs as pulicast`.

    node = pulicast.ThreadedNode("talker", default_namespace="/rover1")
    node["ctrl"] << "Go LEFT!"
    node["pose"].subscribe(lambda pose: print(pose))
    node.start()   # or node.run(), which blocks
    ...
    node.stop()

Differences from 2.x (docs/python.md, "What differs from the 2.x package"):
the node runs (and callbacks are called) from the moment it is made, not
only after `start()`/`run()`; an exception in a callback is printed and
counted rather than ending the node's thread; `stop()` may be called more
than once.
"""

import threading
import warnings
from typing import Callable, Dict, Optional

from . import _native
from .channel import Channel
from .namespace import Namespace, resolve_name

DEFAULT_PORT = _native.DEFAULT_PORT


class ThreadedNode(Namespace):
    """A 2.x-style node, on a pulicast-rs node of its own.

    `node[name]` is a channel (relative to `default_namespace`, or absolute
    with a leading `/`), `node / "child"` a namespace below it,
    `node.make_namespace(path)` a namespace from the root.
    """

    def __init__(
        self,
        name: str,
        port: int = DEFAULT_PORT,
        ttl: int = 0,
        heartbeat_period: float = 0.1,
        interface_address: Optional[str] = None,
        default_namespace: str = "/",
    ):
        self._native = _native.Node(
            name,
            resolve_name("", default_namespace),
            port=port,
            ttl=ttl,
            interface=interface_address,
            heartbeat_period=heartbeat_period,
        )
        self._channels: Dict[str, Channel] = {}
        self._lock = threading.Lock()
        self._running = threading.Event()
        self._stopped = threading.Event()
        # Clear while subscriptions are paused (`pause_subscriptions`).
        self._resumed = threading.Event()
        self._resumed.set()
        self._heartbeat_period = heartbeat_period
        super().__init__(self, default_namespace)

    # How callbacks are called: on their subscriptions' threads.
    _dispatch = None

    def _channel(self, resolved: str) -> Channel:
        with self._lock:
            channel = self._channels.get(resolved)
            if channel is None:
                channel = Channel(self._native.channel("/" + resolved), self._resumed, self._stopped, self._dispatch)
                self._channels[resolved] = channel
            return channel

    @property
    def name(self) -> str:
        """The node's name."""
        return self._native.name

    @property
    def session_id(self) -> int:
        """The node's 2.x session id."""
        return self._native.session_id

    @property
    def heartbeat_period(self) -> float:
        """Seconds between two of the node's heartbeats."""
        return self._heartbeat_period

    def make_namespace(self, namespace: str) -> Namespace:
        """The namespace `namespace`, from the root."""
        return Namespace(self, resolve_name(namespace, "/"))

    def start(self) -> None:
        """Marks the node running (it already receives and announces itself)."""
        if self._running.is_set():
            warnings.warn("Pulicast node already running!")
        self._running.set()

    def run(self) -> None:
        """Blocks until `stop()` (from another thread or a callback); Ctrl-C
        interrupts it."""
        self._running.set()
        while not self._stopped.wait(0.1):
            pass

    def stop(self) -> None:
        """Stops the node: its sockets close and its subscriptions end."""
        self._running.clear()
        self._stopped.set()
        self._native.stop()

    def run_one(self) -> None:
        """Waits one heartbeat period. (Callbacks run on threads of their
        own, not in the thread that calls `run_one` as in 2.x.)"""
        self._stopped.wait(self._heartbeat_period)

    def poll(self) -> None:
        """Nothing to do: callbacks run on threads of their own, as soon as
        their messages come (in 2.x, `poll` runs those that came)."""

    def pause_subscriptions(self) -> None:
        """Holds back every callback of this node's subscriptions until
        `resume_subscriptions()`. Each subscription's queue keeps what
        comes meanwhile, up to its bound (1024 datagrams): a long pause
        loses the oldest, counted in the node's stats, as 2.x loses what
        overflows the socket's buffer. A `NodeDiscoverer` of the node (and
        so a `ChannelDiscoverer`) tells no changes meanwhile either."""
        self._resumed.clear()

    def resume_subscriptions(self) -> None:
        """Lets the callbacks run again, starting with what was held back."""
        self._resumed.set()

    def run_later(self, delay: float, callback: Callable[[], None]) -> None:
        """Calls `callback` on a thread of its own after `delay` seconds."""
        timer = threading.Timer(delay, callback)
        timer.daemon = True
        timer.start()

    def announce_node(self) -> None:
        """Nothing to do: the node announces itself every heartbeat period."""

    def __iter__(self):
        """The channels this node made, as 2.x iterates a node."""
        with self._lock:
            return iter(list(self._channels.values()))

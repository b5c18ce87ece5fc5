"""pulicast_rs: peer-to-peer publish/subscribe for robot fleets, on the
Rust core of pulicast-rs, wire-compatible with Pulicast 2.x.

    import pulicast_rs
    with pulicast_rs.Node("rover_controller", namespace="rover1") as node:
        node.channel("ctrl").publish("Go LEFT!")           # rover1/ctrl, a 2.x string_msg
        for message in node.channel("/rover2/pose").subscribe():
            print(message.value, message.source)

A Pulicast 2.x program runs on it by its import line,
`import pulicast_rs as pulicast`: `ThreadedNode`, `Address`, `serialization`
and `node[channel] << value` are the 2.x API (see `pulicast_threaded`).

See docs/python.md in the repository.
"""

from ._native import (
    DEFAULT_PORT,
    Call,
    CallbackSubscription,
    Channel,
    Client,
    DiscoveryEvent,
    DiscoveryEvents,
    FleetSettings,
    Message,
    Namespace,
    Node,
    OngoingCall,
    PulicastError,
    Server,
    Setting,
    SettingInfo,
    Subscription,
)
import atexit

from . import _native, channel, discovery, puliconf, serialization
from .address import Address
from .pulicast_threaded import ThreadedNode

# Before the interpreter finalizes: nodes' threads then call no more
# callbacks (taking the GIL during finalization would abort the process).
atexit.register(_native._exiting)
# Runs first (last registered): callbacks held back by a paused 2.x node
# let go, so the wait above is not for them.
atexit.register(channel.EXITING.set)



def __getattr__(name: str):
    # `pulicast_rs.TrioNode` as 2.x's `pulicast.TrioNode`, with Trio
    # imported only by programs that use it.
    if name == "TrioNode":
        try:
            from .pulicast_trio import TrioNode
        except ImportError as e:
            # An AttributeError, so `hasattr` is False; `from pulicast_rs
            # import TrioNode` turns it into an ImportError with this text.
            raise AttributeError(f"TrioNode needs Trio: pip install trio ({e})") from e
        return TrioNode
    raise AttributeError(f"module 'pulicast_rs' has no attribute {name!r}")


__all__ = [
    "Address",
    "ThreadedNode",
    "discovery",
    "puliconf",
    "serialization",
    "DEFAULT_PORT",
    "Call",
    "CallbackSubscription",
    "Channel",
    "Client",
    "DiscoveryEvent",
    "DiscoveryEvents",
    "FleetSettings",
    "Message",
    "Namespace",
    "Node",
    "OngoingCall",
    "PulicastError",
    "Server",
    "Setting",
    "SettingInfo",
    "Subscription",
]

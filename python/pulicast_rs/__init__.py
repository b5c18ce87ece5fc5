"""pulicast_rs: peer-to-peer publish/subscribe for robot fleets, on the
Rust core of pulicast-rs, wire-compatible with Pulicast 2.x.

    import pulicast_rs
    with pulicast_rs.Node("rover_controller", namespace="rover1") as node:
        node.channel("ctrl").publish("Go LEFT!")           # rover1/ctrl, a 2.x string_msg
        for message in node.channel("/rover2/pose").subscribe():
            print(message.value, message.source)

See docs/python.md in the repository.
"""

from ._native import (
    DEFAULT_PORT,
    CallbackSubscription,
    Channel,
    Message,
    Namespace,
    Node,
    PulicastError,
    Subscription,
)

__all__ = [
    "DEFAULT_PORT",
    "CallbackSubscription",
    "Channel",
    "Message",
    "Namespace",
    "Node",
    "PulicastError",
    "Subscription",
]

"""`TrioNode`: the Pulicast 2.x node for Trio programs, on pulicast-rs, so
that a 2.x Trio program runs by its import line (`trio` must be installed:
`pip install trio`).

    async with trio.open_nursery() as nursery:
        node = pulicast.TrioNode("listener", nursery)
        async with open_subscription(node["chatter"], str) as messages:
            async for message in messages:
                print(message)

Callbacks run in the Trio thread, as in 2.x: the subscription's thread
hands each message to Trio (`trio.from_thread.run_sync`) and waits until
it ran, so a slow callback holds the subscription's queue back, not Trio.
"""

from typing import Any, Callable, Optional

import trio

from .channel import ALL_MESSAGES_LEAD_VALUE, ORDERED_MESSAGE_LEAD_VALUE, Channel
from .pulicast_threaded import DEFAULT_PORT, ThreadedNode


class TrioNode(ThreadedNode):
    """A 2.x-style node whose callbacks run in the Trio run that made it.

    Made inside `trio.run` (it takes the run's token); `nursery` runs what
    `run_later` schedules. `stopped` is a `trio.Event` set by `stop()`.
    """

    def __init__(
        self,
        name: str,
        nursery: "trio.Nursery",
        port: int = DEFAULT_PORT,
        ttl: int = 0,
        heartbeat_period: float = 0.1,
        interface_address: Optional[str] = None,
        default_namespace: str = "/",
    ):
        self._nursery = nursery
        self._token = trio.lowlevel.current_trio_token()
        super().__init__(
            name,
            port=port,
            ttl=ttl,
            heartbeat_period=heartbeat_period,
            interface_address=interface_address,
            default_namespace=default_namespace,
        )
        self.stopped = trio.Event()
        self._running.set()
        # As 2.x's announcing task, this keeps the nursery open while the
        # node runs, and stops the node when the nursery is cancelled.
        nursery.start_soon(self._live)

    async def _live(self) -> None:
        try:
            await self.stopped.wait()
        finally:
            if not self._stopped.is_set():
                ThreadedNode.stop(self)

    def _dispatch(self, callback: Callable, message: Any) -> None:
        """Runs `callback(message)` in the Trio thread, from a
        subscription's thread. Once the Trio run ended, nothing runs."""
        try:
            trio.from_thread.run_sync(callback, message, trio_token=self._token)
        except trio.RunFinishedError:
            pass

    @property
    def nursery(self) -> "trio.Nursery":
        """The nursery `run_later` starts its tasks in."""
        return self._nursery

    def stop(self) -> None:
        """Stops the node (from the Trio thread): its sockets close, its
        subscriptions end, and `stopped` is set, which lets the nursery
        close. Cancelling the nursery stops the node too."""
        super().stop()
        self.stopped.set()

    def run_later(self, delay: float, callback: Callable[[], None]) -> None:
        """Calls `callback` in the Trio thread after `delay` seconds."""

        async def later():
            await trio.sleep(delay)
            callback()

        self._nursery.start_soon(later)


def open_subscription(channel: Channel, message_type: type = Any,
                      min_lead=ALL_MESSAGES_LEAD_VALUE) -> "trio.MemoryReceiveChannel":
    """A Trio memory channel of the messages on `channel` (of
    `message_type`: `Any` for all, as `subscribe` reads annotations):
    `await messages.receive()`, `async for`, or `async with` to close it.
    The pulicast subscription ends with the next message after it closed.
    """
    send, receive = trio.open_memory_channel(float("inf"))

    def on_message(message: message_type):
        try:
            send.send_nowait(message)
        except trio.BrokenResourceError:
            handle.unsubscribe()

    handle = channel.subscribe(on_message, min_lead=min_lead, with_handle=True)
    return receive


def open_ordered_subscription(channel: Channel, message_type: type = Any) -> "trio.MemoryReceiveChannel":
    """Like `open_subscription`, with only the messages that come in order."""
    return open_subscription(channel, message_type, ORDERED_MESSAGE_LEAD_VALUE)


async def next_message_on(channel: Channel, message_type: type = Any, min_lead=ALL_MESSAGES_LEAD_VALUE):
    """The next message on `channel`."""
    async with open_subscription(channel, message_type=message_type, min_lead=min_lead) as messages:
        async for message in messages:
            return message


async def next_ordered_message_on(channel: Channel, message_type: type = Any):
    """Like `next_message_on`, with only a message that comes in order.
    (2.x's returns nothing: this one returns the message.)"""
    return await next_message_on(channel, message_type, ORDERED_MESSAGE_LEAD_VALUE)

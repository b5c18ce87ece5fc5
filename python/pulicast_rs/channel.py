"""Channels as Pulicast 2.x programs use them: `channel << value`, and
`subscribe(callback)` where the callback's signature and the annotation of
its message parameter pick what it receives (see `subscribe`)."""

import functools
import inspect
import logging
import math
import typing
import threading
import weakref
from typing import Any, Callable, Optional

from . import serialization
from .address import Address

_log = logging.getLogger("pulicast_rs")

# `min_lead` of all messages, and of messages in order only.
ALL_MESSAGES_LEAD_VALUE = -math.inf
ORDERED_MESSAGE_LEAD_VALUE = 1


def _optional_of(t):
    """`T` if `t` is `typing.Optional[T]`, else None: only `typing.Union`
    with `None` last counts, as in 2.x."""
    if typing.get_origin(t) is typing.Union:
        args = typing.get_args(t)
        if args and args[-1] is type(None):
            return args[0]
    return None


class SubscriptionHandle:
    """A subscription's handle (`subscribe(..., with_handle=True)`): it ends
    with `unsubscribe()`, or when the handle is garbage collected."""

    def __init__(self, native):
        self._finalizer = weakref.finalize(self, native.close)

    def unsubscribe(self) -> None:
        """Ends the subscription (a second call does nothing)."""
        self._finalizer()


class Channel:
    """One channel of a 2.x-style node: made by `node[name]` or `ns[name]`."""

    def __init__(self, native_channel, gate: Optional[threading.Event] = None,
                 stopped: Optional[threading.Event] = None,
                 dispatch: Optional[Callable[[Callable, Any], None]] = None):
        self._native = native_channel
        # How a callback is called: on the subscription's thread (None), or
        # handed to an event loop (a `TrioNode`'s).
        self._dispatch = dispatch
        # Set while the node's subscriptions run (`pause_subscriptions`
        # clears it), and set once the node stopped; None: never paused.
        self._gate = gate
        self._stopped = stopped or threading.Event()
        self._subscriptions = []  # those without a handle: they live as long as the channel
        self._live = 0
        self._published = False
        # How often the program means to publish, in seconds (announced by
        # 2.x in its heartbeats; pulicast-rs measures the period instead).
        self.publishing_period = 0.0

    @property
    def name(self) -> str:
        """The resolved name (no leading or trailing `/`)."""
        return self._native.name

    @property
    def is_subscribed(self) -> bool:
        """Whether this node subscribes the channel."""
        return self._live > 0

    @property
    def is_published(self) -> bool:
        """Whether this node published on the channel."""
        return self._published

    def publish(self, data) -> None:
        """Publishes `data` (bytes-like) as it is, with no type."""
        self._native.publish_bytes(bytes(bytearray(data)))
        self._published = True

    def publish_message(self, message) -> None:
        """Publishes `message`, encoded by its exact type (see
        `pulicast_rs.serialization`); `KeyError` for a type with no encoder."""
        self._native.publish_bytes(serialization.encode(message))
        self._published = True

    def __lshift__(self, message):
        self.publish_message(message)

    def subscribe(self, callback: Callable, min_lead=ALL_MESSAGES_LEAD_VALUE, with_handle: bool = False):
        """Calls `callback` with each message that arrives, as 2.x does.

        The callback's signature picks what it gets: none (called for every
        packet), or a message parameter (the first) and optionally `lead`
        and `source`, by those names, in any order. The message parameter's
        annotation picks the messages: `int`, `float`, `bool`, `str`,
        `bytes` (the raw payload), a registered ZCM class, nothing or `Any`
        (all that decode); `Optional[...]` delivers `None` for a message that
        does not decode instead of dropping it. Messages with a lead below
        `min_lead` are dropped. Raises `ValueError` for an annotation that
        can't be received. Returns a `SubscriptionHandle` if `with_handle`,
        else None (the subscription then lasts as long as the channel).

        Unlike 2.x, the callback runs on a thread of the channel's
        subscription from the moment it is subscribed (not only once `start()` or `run()` is
        called), and an exception in it is printed and counted, not raised
        out of the node's thread.
        """
        spec = inspect.getfullargspec(callback)
        args = list(spec.args)
        # A method's `self`, by its name (as 2.x does).
        if args and args[0] == "self":
            args.pop(0)
        if not args:

            def bare(message):
                if message.lead >= min_lead:
                    callback()

            return self._subscribe(bare, with_handle)

        name = args[0]
        annotation = spec.annotations.get(name, Any)
        wrapped = _optional_of(annotation)
        deliver_none = wrapped is not None
        message_type = wrapped if deliver_none else annotation
        try:
            decoder = serialization.get_message_decoder(message_type)
        except KeyError:
            raise ValueError(f"Unsupported message type: {message_type}!") from None
        if "lead" in spec.annotations and spec.annotations["lead"] is not int:
            raise ValueError(f"The lead argument must be an integer, not {spec.annotations['lead']}!")
        if "source" in spec.annotations and spec.annotations["source"] is not Address:
            raise ValueError(
                f"The source argument must be a pulicast_rs Address, not {spec.annotations['source']}!"
            )
        wants_lead = "lead" in args
        wants_source = "source" in args
        channel = self.name

        def decoding(message):
            if message.lead < min_lead:
                _log.warning(
                    "Dropping message on %s since its lead %s is smaller than the minimum lead %s!",
                    channel,
                    message.lead,
                    min_lead,
                )
                return
            value = decoder(message.payload)
            if value is None and not deliver_none:
                _log.info("Dropping message on %s since there was a decoding error!", channel)
                return
            kwargs = {name: value}
            if wants_lead:
                kwargs["lead"] = message.lead
            if wants_source:
                kwargs["source"] = Address.parse(message.source)
            callback(**kwargs)

        return self._subscribe(decoding, with_handle)

    def subscribe_ordered(self, callback: Callable, with_handle: bool = False):
        """Like `subscribe`, for messages in order only (lead >= 1)."""
        return self.subscribe(callback, ORDERED_MESSAGE_LEAD_VALUE, with_handle)

    def _subscribe(self, on_message, with_handle: bool) -> Optional[SubscriptionHandle]:
        closed = threading.Event()
        stopped = self._stopped

        def over() -> bool:
            return closed.is_set() or stopped.is_set() or EXITING.is_set()

        if self._gate is not None or self._dispatch is not None:
            # Checked where the callback runs: once the subscription ended
            # or the node stopped, a message handed over (to Trio) before
            # is not delivered.
            on_message = functools.partial(_unless, over, on_message)
        if self._dispatch is not None:
            on_message = functools.partial(self._dispatch, on_message)
        if self._gate is not None:
            on_message = _gated(on_message, self._gate, over)
        native = self._native.subscribe(on_message)
        self._live += 1
        channel = weakref.ref(self)

        def ended(close=native.close):
            closed.set()
            close()
            c = channel()
            if c is not None:
                c._live -= 1

        holder = _Closer(ended)
        if with_handle:
            return SubscriptionHandle(holder)
        self._subscriptions.append(holder)
        return None

    def __repr__(self):
        return f"Channel({self.name!r})"


# Set by the package's exit hook: a callback held back by a pause lets go
# before the interpreter finalizes (a thread still in Python then would
# abort the process).
EXITING = threading.Event()


def _unless(over: Callable[[], bool], on_message, message) -> None:
    if not over():
        on_message(message)


def _gated(on_message, gate: threading.Event, over: Callable[[], bool]):
    """`on_message`, held back while `gate` is clear (the node's
    subscriptions paused): the subscription's queue holds what comes
    meanwhile, up to its bound, the oldest dropped (and counted) past it.
    Once `over()` (the subscription ended, the node stopped), nothing
    more is called."""

    def gated(message):
        while not gate.wait(0.1):
            if over():
                return
        if not over():
            on_message(message)

    return gated


class _Closer:
    """Closes a native subscription once."""

    def __init__(self, close):
        self._close = close
        self._closed = False

    def close(self):
        if not self._closed:
            self._closed = True
            self._close()

"""`NodeDiscoverer`: every live member of the fleet as a `NodeView`, by
session id, as 2.x's `pulicast.discovery.node_discoverer` gives them."""

import threading
import traceback

from .node_view import NodeView
from .observable import ObservableDict


class NodeDiscoverer(ObservableDict):
    """An observable dict from session id to `NodeView` of every live node
    (this one included): `add_on_item_added_callback(f)` and
    `add_on_item_removed_callback(f)` tell joins and leaves.

    It reads the node's discovery (gossip members, 2.x peers, members a
    bridge relays) every heartbeat period, on a thread of its own, which
    runs the callbacks. It stops with its node, or `stop()`.
    """

    def __init__(self, node):
        super().__init__()
        native = getattr(node, "_native", node)
        self._native = native
        self._period = float(getattr(node, "heartbeat_period", 0.1) or 0.1)
        self._stopped = threading.Event()
        # Reentrant: a callback (run under it) may make a ChannelDiscoverer.
        self._lock = threading.RLock()
        # A 2.x node's pause holds the discoverer's callbacks back too, as
        # 2.x's pause stops its one receive loop.
        self._resumed = getattr(node, "_resumed", None)
        self._read()
        self._thread = threading.Thread(target=self._run, name="pulicast_rs NodeDiscoverer", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        with self._lock:
            if self._native.stopped:
                return
            live = {}
            for member in self._native.members(include_self=True):
                if member["state"] in ("alive", "suspect"):
                    live[member["key"]] = member
            for key in [k for k in dict.keys(self) if k not in live]:
                del self[key]
            for key, member in live.items():
                view = dict.get(self, key)
                if view is None:
                    self[key] = NodeView(member, self._period)
                else:
                    view.update(member)

    def _run(self) -> None:
        while not self._stopped.wait(self._period):
            if self._native.stopped:
                return
            if self._resumed is not None and not self._resumed.is_set():
                continue
            try:
                self._read()
            except Exception as e:  # shown; the discoverer goes on
                traceback.print_exception(type(e), e, e.__traceback__)

    def stop(self) -> None:
        """Stops watching the fleet."""
        self._stopped.set()

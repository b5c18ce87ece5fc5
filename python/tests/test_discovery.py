"""Discovery from Python: members, the stream of fleet changes, and 2.x's
`NodeDiscoverer` (with a 2.x reference node among the members)."""

import subprocess
import threading

import pulicast_rs as pulicast
from conftest import WAIT, eventually
from pulicast_rs.discovery.node_discoverer import NodeDiscoverer
from pulicast_rs.discovery.observable import ObservableDict, ObservableSet
from test_compat import REPO, reference_python  # noqa: F401 (a fixture)


def test_members_and_the_changes_of_the_fleet(make_node):
    watcher = make_node("watcher")
    events = watcher.discovery_events()
    assert events.recv(timeout=0.05) is None
    me = watcher.members(include_self=True)[0]
    assert (me["name"], me["key"], me["state"]) == ("watcher", watcher.session_id, "alive")

    rover = make_node("rover", "rover1")
    pose = rover.channel("pose")
    pose.publish(1.0)

    seen = {}
    while set(seen) < {"joined", "channel_appeared"}:
        event = events.recv(timeout=WAIT)
        assert event is not None, f"no more events after {seen}"
        if event.name == "rover":
            seen.setdefault(event.kind, event)
    assert seen["joined"].key == rover.session_id
    assert seen["joined"].member["namespace"] == "rover1"
    assert seen["channel_appeared"].channel is not None

    def rover_publishes_pose():
        rovers = [m for m in watcher.members() if m["name"] == "rover"]
        return bool(rovers) and "rover1/pose" in rovers[0]["publishes"]

    eventually("the rover's channel", rover_publishes_pose)

    rover.stop()
    while True:
        event = events.recv(timeout=WAIT)
        assert event is not None, "the rover's leaving was never told"
        if event.name == "rover" and event.kind in ("left", "failed"):
            break
    assert events.missed == 0


def test_the_2x_node_discoverer_tells_joins_and_leaves(make_node, port, reference_python):  # noqa: F811
    node = pulicast.ThreadedNode("py2x", port=port, interface_address="127.0.0.1")
    try:
        discoverer = NodeDiscoverer(node)
        assert isinstance(discoverer, ObservableDict)
        eventually("itself", lambda: node.session_id in discoverer)
        added, removed = [], []
        lock = threading.Lock()

        def on_added(view):
            with lock:
                added.append(view.name)

        def raising(view):
            raise RuntimeError("a bug in one callback")

        # One callback that raises: the others are still told.
        discoverer.add_on_item_added_callback(raising, call_on_existing_items=False)
        discoverer.add_on_item_added_callback(on_added)
        discoverer.add_on_item_removed_callback(lambda view: removed.append(view.name))
        assert added == ["py2x"]  # the items there are told at once

        other = make_node("native")
        other.channel("chatter").publish("hi")
        sub = other.channel("orders").subscribe()
        eventually("the native node", lambda: "native" in added)
        view = discoverer[other.session_id]
        assert view.name == "native" and view.deadline > 0
        assert isinstance(view.channels, ObservableSet)
        eventually("its channels", lambda: "chatter" in view.publications and "orders" in view.subscriptions)
        assert [p.name for p in view.publications] == ["chatter"]  # iterating yields the values
        assert view.source is not None and view.source.port > 0

        # A node of the 2.x reference package is a member like any other.
        peer = subprocess.Popen(
            [reference_python, str(REPO / "tests/python/peer.py"), "subscribe", "--port", str(port), "--name", "ref2x",
             "--channel", "x", "--count", "1000", "--timeout", "30"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        try:
            eventually("the 2.x node", lambda: "ref2x" in added, within=30)
        finally:
            peer.kill()
            peer.wait()
        eventually("the 2.x node gone", lambda: "ref2x" in removed, within=30)

        sub.close()
        other.stop()
        eventually("the native node gone", lambda: "native" in removed)
        assert other.session_id not in discoverer
        discoverer.stop()
    finally:
        node.stop()


def test_the_2x_channel_discoverer_tells_channels_and_who_uses_them(make_node, port):
    from pulicast_rs.discovery.channel_discoverer import ChannelDiscoverer
    from pulicast_rs.discovery.channel_view import ChannelView

    node = pulicast.ThreadedNode("py2x_channels", port=port, interface_address="127.0.0.1")
    try:
        nodes = NodeDiscoverer(node)
        channels = ChannelDiscoverer(nodes)
        appeared, gone = [], []
        channels.add_on_item_added_callback(lambda view: appeared.append(view.name))
        channels.add_on_item_removed_callback(lambda view: gone.append(view.name))

        talker = make_node("talker", "rover1")
        talker.channel("pose").publish(1.0)
        listener = make_node("listener")
        sub = listener.channel("/rover1/pose").subscribe()
        orders = listener.channel("orders").subscribe()
        eventually("rover1/pose", lambda: "rover1/pose" in appeared and "orders" in appeared)
        pose = channels["rover1/pose"]
        assert isinstance(pose, ChannelView) and pose.name == "rover1/pose"
        eventually("who uses it", lambda: {v.name for v in pose.publishers} == {"talker"}
                   and {v.name for v in pose.subscribers} == {"listener"})
        assert {v.name for v in pose.nodes} == {"talker", "listener"}

        # A channel goes when the last node that used it leaves.
        sub.close()
        orders.close()
        listener.stop()
        eventually("orders gone", lambda: "orders" in gone)
        assert "rover1/pose" in channels  # talker still publishes it
        eventually("the listener out of it", lambda: not pose.subscribers)
        talker.stop()
        eventually("rover1/pose gone", lambda: "rover1/pose" in gone)
        nodes.stop()
    finally:
        node.stop()

"""`ChannelDiscoverer`: every channel in use in the fleet as a
`ChannelView`, by name, as 2.x's `pulicast.discovery.channel_discoverer`
gives them."""

import contextlib

from .channel_view import ChannelView
from .node_discoverer import NodeDiscoverer
from .node_view import NodeView, Publication
from .observable import ObservableDict


class ChannelDiscoverer(ObservableDict):
    """An observable dict from channel name to `ChannelView`, kept from a
    `NodeDiscoverer`'s views: a channel appears when a node first
    publishes or subscribes it, and goes when the last node that did
    leaves. Its callbacks run on the node discoverer's thread.

    One difference from 2.x: a node that leaves is also taken out of each
    channel's `nodes` (2.x leaves it there).
    """

    def __init__(self, node_discoverer: NodeDiscoverer):
        super().__init__()
        # Under the discoverer's lock: no join or leave falls between the
        # views there now and the callbacks for those to come.
        lock = getattr(node_discoverer, "_lock", None) or contextlib.nullcontext()
        with lock:
            node_discoverer.add_on_item_added_callback(self._on_node_added)
            node_discoverer.add_on_item_removed_callback(self._on_node_left)

    def _view(self, name: str) -> ChannelView:
        view = dict.get(self, name)
        if view is None:
            view = ChannelView(name)
            self[name] = view
        return view

    def _on_node_added(self, node: NodeView) -> None:
        def subscribed(name: str) -> None:
            self._view(name).subscribers.add(node)

        def published(publication: Publication) -> None:
            self._view(publication.name).publishers.add(node)

        def used(name: str) -> None:
            self._view(name).nodes.add(node)

        node.subscriptions.add_on_item_added_callback(subscribed)
        node.publications.add_on_item_added_callback(published)
        node.channels.add_on_item_added_callback(used)

    def _on_node_left(self, node: NodeView) -> None:
        for name in list(node.channels):
            view = dict.get(self, name)
            if view is None:
                continue
            view.subscribers.discard(node)
            view.publishers.discard(node)
            view.nodes.discard(node)
            if not view.subscribers and not view.publishers:
                del self[name]

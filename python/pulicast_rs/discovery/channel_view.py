"""`ChannelView`: a channel in use in the fleet, as 2.x's channel
discoverer shows it."""

from .node_view import NodeView
from .observable import ObservableSet


class ChannelView:
    """A channel's name and the `NodeView`s of the nodes that publish it,
    subscribe it, or use it either way (`nodes`), each an observable set."""

    def __init__(self, name: str):
        self.name = name
        self.subscribers: ObservableSet[NodeView] = ObservableSet()
        self.publishers: ObservableSet[NodeView] = ObservableSet()
        self.nodes: ObservableSet[NodeView] = ObservableSet()

    def __repr__(self):
        return f"ChannelView({self.name!r}, publishers={len(self.publishers)}, subscribers={len(self.subscribers)})"

"""`NodeView`: a member of the fleet as 2.x's node discoverer shows it."""

import time
from typing import Optional

from ..address import Address
from .observable import ObservableDict, ObservableSet


class Publication:
    """That a node publishes on a channel, with its period in seconds."""

    __slots__ = "name", "period"

    def __init__(self, name: str, period: float):
        self.name = name
        self.period = period

    def __repr__(self):
        return f"Publication({self.name!r}, {self.period})"


def _address(text: Optional[str]) -> Optional[Address]:
    if not text:
        return None
    ip, _, port = text.rpartition(":")
    return Address(ip, int(port))


class NodeView:
    """A member of the fleet: its name, session id, where its messages come
    from, and its channels (sets that only grow, as in 2.x)."""

    def __init__(self, member: dict, heartbeat_period: float):
        self._name = member["name"]
        self._session_id = member["key"]
        self._source = _address(member.get("data_address") or member["address"])
        self._heartbeat_period = heartbeat_period
        self._subscriptions: ObservableSet[str] = ObservableSet()
        self._publications: ObservableDict[str, Publication] = ObservableDict()
        self._channels: ObservableSet[str] = ObservableSet()
        self._deadline = 0.0
        self.update(member)

    def update(self, member: dict) -> None:
        """Takes in what discovery says of the member now."""
        periods = member.get("periods", {})
        for name in member["publishes"]:
            known = dict.get(self._publications, name)
            if known is None:
                self._publications[name] = Publication(name, periods.get(name, 0.0))
            else:
                # Measured after it was first seen.
                known.period = periods.get(name, known.period)
            self._channels.add(name)
        for name in member["subscribes"]:
            self._subscriptions.add(name)
            self._channels.add(name)
        self._deadline = time.time() + 3 * self._heartbeat_period

    @property
    def name(self) -> str:
        return self._name

    @property
    def session_id(self) -> int:
        return self._session_id

    @property
    def source(self) -> Optional[Address]:
        """Where its messages come from."""
        return self._source

    @property
    def heartbeat_period(self) -> float:
        """How often the discoverer hears of it, in seconds."""
        return self._heartbeat_period

    @property
    def deadline(self) -> float:
        """When it counts as dead unless it is heard of again (epoch s)."""
        return self._deadline

    @property
    def is_dead(self) -> bool:
        return time.time() > self._deadline

    @property
    def subscriptions(self) -> ObservableSet:
        return self._subscriptions

    @property
    def publications(self) -> ObservableDict:
        return self._publications

    @property
    def channels(self) -> ObservableSet:
        return self._channels

    def __repr__(self):
        return f"NodeView({self._name!r}, {self._session_id})"

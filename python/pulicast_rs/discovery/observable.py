"""2.x's observable containers: a dict and a set that tell callbacks what
is added and removed (`pulicast.core.utils.observable_dict` and
`observable_set`)."""

import traceback
from typing import Callable, Generic, List, TypeVar

K = TypeVar("K")
V = TypeVar("V")


class _Observers:
    def __init__(self):
        self._added: List[Callable] = []
        self._removed: List[Callable] = []

    def add_on_item_added_callback(self, callback: Callable, call_on_existing_items: bool = True) -> None:
        """Calls `callback(item)` for each item added (and, by default, for
        those there now)."""
        self._added.append(callback)
        if call_on_existing_items:
            for item in list(self._items()):
                callback(item)

    def add_on_item_removed_callback(self, callback: Callable) -> None:
        """Calls `callback(item)` for each item removed."""
        self._removed.append(callback)

    def remove_on_item_added_callback(self, callback: Callable) -> None:
        self._added.remove(callback)

    def remove_on_item_removed_callback(self, callback: Callable) -> None:
        self._removed.remove(callback)

    def is_observed(self) -> bool:
        """Whether any callback is registered."""
        return bool(self._added or self._removed)

    def _tell_added(self, item) -> None:
        for callback in list(self._added):
            _call(callback, item)

    def _tell_removed(self, item) -> None:
        for callback in list(self._removed):
            _call(callback, item)


def _call(callback: Callable, item) -> None:
    """Calls one callback; its exception is shown, and the others are
    still told (2.x raises it into the thread that changed the container)."""
    try:
        callback(item)
    except Exception as e:
        traceback.print_exception(type(e), e, e.__traceback__)


class ObservableDict(dict, _Observers, Generic[K, V]):
    """A dict whose added and removed values are told; iterating it yields
    its values, as in 2.x. Setting a key that is there changes nothing."""

    def __init__(self, *args, **kwargs):
        dict.__init__(self, *args, **kwargs)
        _Observers.__init__(self)

    def _items(self):
        return dict.values(self)

    def __iter__(self):
        return iter(list(dict.values(self)))

    def __setitem__(self, key, value):
        if key in self:
            return
        dict.__setitem__(self, key, value)
        self._tell_added(value)

    def __delitem__(self, key):
        value = dict.__getitem__(self, key)
        dict.__delitem__(self, key)
        self._tell_removed(value)

    def pop(self, key, *default):
        if key not in self:
            return dict.pop(self, key, *default)
        value = dict.pop(self, key)
        self._tell_removed(value)
        return value

    def clear(self):
        values = list(dict.values(self))
        dict.clear(self)
        for value in values:
            self._tell_removed(value)

    def popitem(self):
        raise NotImplementedError

    def update(self, *args, **kwargs):
        raise NotImplementedError


class ObservableSet(set, _Observers, Generic[K]):
    """A set whose added and removed items are told."""

    def __init__(self, *args):
        set.__init__(self, *args)
        _Observers.__init__(self)

    def _items(self):
        return set(self)

    def add(self, item):
        if item not in self:
            set.add(self, item)
            self._tell_added(item)

    def remove(self, item):
        set.remove(self, item)
        self._tell_removed(item)

    def discard(self, item):
        if item in self:
            self.remove(item)

    def pop(self):
        item = set.pop(self)
        self._tell_removed(item)
        return item

    def update(self, *others):
        for other in others:
            for item in other:
                self.add(item)

    def symmetric_difference_update(self, other):
        for item in set(other):
            if item in self:
                self.remove(item)
            else:
                self.add(item)

    def difference_update(self, *others):
        raise NotImplementedError

    def intersection_update(self, *others):
        raise NotImplementedError

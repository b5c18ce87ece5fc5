"""Namespaces as Pulicast 2.x programs use them: `ns[name]` for a channel,
`ns / child` for a namespace below, names resolved as POSIX paths."""

import posixpath


def resolve_name(name: str, namespace: str = "/") -> str:
    """`name` in `namespace`, as 2.x resolves it: a leading `/` starts at the
    root, `..` goes up (never past the root), repeated and trailing `/` and
    `.` parts go; no leading or trailing `/` in the result.

    >>> resolve_name("speed", "/robot"), resolve_name("/a/b", "/x"), resolve_name("../../x", "/robot")
    ('robot/speed', 'a/b', 'x')
    """
    base = posixpath.normpath(posixpath.join("/", namespace))
    resolved = posixpath.normpath(posixpath.join(base, name))
    # normpath keeps a leading "//" (POSIX allows it a meaning): not here.
    return resolved.strip("/")


class Namespace:
    """A place in the channel hierarchy of a 2.x-style node."""

    def __init__(self, node, path: str = "/"):
        self._node = node
        self._path = path

    def __getitem__(self, name: str):
        """The channel `name` in this namespace."""
        return self._node._channel(resolve_name(name, self._path))

    def __truediv__(self, child: str) -> "Namespace":
        """The namespace `child` below this one."""
        return Namespace(self._node, resolve_name(child, self._path))

    def __str__(self):
        return self._path

    def __repr__(self):
        return self._path

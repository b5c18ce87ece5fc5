"""`Address`: where a message came from, as 2.x programs receive it."""


class Address:
    """A sender's socket address: `ip` (dotted quad, a `str`) and `port`.

    The 2.x package's `Address`, which 2.x callbacks annotate their `source`
    parameter with.
    """

    __slots__ = ("ip", "port")

    def __init__(self, ip: str, port: int):
        self.ip = ip
        self.port = port

    @classmethod
    def parse(cls, text: str) -> "Address":
        """From `"ip:port"`, as the native `Message.source` gives it."""
        ip, _, port = text.rpartition(":")
        return cls(ip, int(port))

    def __eq__(self, other):
        return isinstance(other, Address) and (self.ip, self.port) == (other.ip, other.port)

    def __ne__(self, other):
        return not self == other

    def __hash__(self):
        return hash((self.ip, self.port))

    def __repr__(self):
        return f"ip: {self.ip}\tport: {self.port}"

"""Helpers for the tests: every node on loopback (127.0.0.1, TTL 0), on a
port of its own test, and every wait bounded."""

import socket
import time

import pytest

import pulicast_rs

WAIT = 5.0


def free_port() -> int:
    """A UDP port nothing on this host uses right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def make_node(port):
    """Starts nodes on the test's port; stops them at the end."""
    nodes = []

    def make(name: str, namespace: str = "", **kwargs) -> pulicast_rs.Node:
        node = pulicast_rs.Node(
            name, namespace, port=port, interface="127.0.0.1", keys_from_env=False, **kwargs
        )
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        node.stop()


def eventually(what: str, condition, within: float = WAIT):
    """Waits until `condition()` is true, at most `within` seconds."""
    deadline = time.monotonic() + within
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)

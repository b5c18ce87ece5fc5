"""The 2.x-compatible API: a 2.x program on pulicast_rs (its import line
changed) and the same program on the reference package talk both ways,
and the 2.x subscription rules hold in one process."""

import collections
import gc
import json
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Optional

import pytest

import pulicast_rs as pulicast
from conftest import WAIT, eventually

REPO = Path(__file__).resolve().parents[2]
PROGRAMS = Path(__file__).resolve().parent / "programs"
CHATTER = PROGRAMS / "chatter.py"
COUNT = 60


@pytest.fixture(scope="session")
def reference_python() -> str:
    """The venv of the 2.x reference package (pulicast==2.0.1), as the Rust
    interop tests set it up (tests/python/setup_venv.sh)."""
    setup = subprocess.run(
        ["bash", str(REPO / "tests/python/setup_venv.sh")],
        capture_output=True,
        text=True,
        timeout=900,
    )
    if setup.returncode != 0:
        pytest.fail(f"the 2.x reference venv could not be set up:\n{setup.stderr}")
    return setup.stdout.strip().splitlines()[-1]


@pytest.fixture
def chatter_rs(tmp_path) -> Path:
    """chatter.py with its import line, and nothing else, changed."""
    text = CHATTER.read_text()
    changed = text.replace("\nimport pulicast\n", "\nimport pulicast_rs as pulicast\n", 1)
    assert changed != text
    path = tmp_path / "chatter_rs.py"
    path.write_text(changed)
    return path


def exchange(listener_cmd, talker_cmd):
    """Starts the listener, waits for it to subscribe, runs the talker, and
    returns the listener's JSON lines by channel."""
    listener = subprocess.Popen(
        listener_cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        ready = threading.Event()
        errors = []

        def read_stderr():
            for line in listener.stderr:
                errors.append(line)
                if line.startswith("READY"):
                    ready.set()

        reader = threading.Thread(target=read_stderr, daemon=True)
        reader.start()
        assert ready.wait(60), f"the listener never got ready: {''.join(errors)}"
        talker = subprocess.run(talker_cmd, capture_output=True, text=True, timeout=120)
        assert talker.returncode == 0, talker.stderr
        out, _ = listener.communicate(timeout=120)
    finally:
        if listener.poll() is None:
            listener.kill()
            listener.wait()
    assert listener.returncode == 0, "".join(errors)
    got = collections.defaultdict(list)
    for line in out.splitlines():
        record = json.loads(line)
        got[record["channel"]].append(record)
    return got


def check_received(got):
    """What chatter's listener prints for chatter's talker's COUNT rounds:
    each type by its annotation, nearly all of them (loopback loses none,
    but a first message may beat a subscription's join)."""

    def values(channel):
        return [r["value"] for r in got[channel]]

    at_least = COUNT - 5
    ints = values("ints")
    assert len(ints) >= at_least and all(type(v) is int for v in ints), ints
    assert all(r["lead"] >= 1 and r["port"] > 0 for r in got["ints"])
    floats = values("floats")
    assert len(floats) >= at_least and all(type(v) is float and v % 1 == 0.5 for v in floats)
    texts = values("texts")
    assert len(texts) >= at_least and all(t.startswith("hi ") for t in texts)
    assert texts == sorted(texts, key=lambda t: int(t[3:])), "ordered: in order"
    flags = values("flags")
    assert len(flags) >= at_least and set(flags) == {True, False}
    raw = values("raw")
    assert len(raw) >= at_least and all(len(h) == 4 and h.endswith("ff") for h in raw)
    vecs = values("vecs")
    assert len(vecs) >= at_least and all(x == -y for x, y in vecs)
    assert set(values("vecs_any")) == {"Vec2"}
    assert set(values("texts_as_int")) == {None}


def test_a_2x_program_on_pulicast_rs_hears_the_same_program_on_2x(reference_python, chatter_rs, port):
    run_2x = [reference_python, str(PROGRAMS / "run_2x.py"), str(CHATTER)]
    got = exchange(
        [sys.executable, str(chatter_rs), "listener", str(port), "6"],
        run_2x + ["talker", str(port), str(COUNT)],
    )
    check_received(got)


def test_the_2x_program_hears_it_on_pulicast_rs(reference_python, chatter_rs, port):
    run_2x = [reference_python, str(PROGRAMS / "run_2x.py"), str(CHATTER)]
    got = exchange(
        run_2x + ["listener", str(port), "6"],
        [sys.executable, str(chatter_rs), "talker", str(port), str(COUNT)],
    )
    check_received(got)


@pytest.fixture
def node2x(port):
    nodes = []

    def make(name, **kwargs):
        node = pulicast.ThreadedNode(name, port=port, interface_address="127.0.0.1", **kwargs)
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        node.stop()


def until_heard(channel, value, heard):
    """Publishes `value` until `heard` has something, within WAIT."""
    deadline = time.monotonic() + WAIT
    while not heard and time.monotonic() < deadline:
        channel << value
        time.sleep(0.02)
    assert heard, f"nothing heard on {channel.name}"


def test_signatures_pick_what_a_callback_gets(node2x):
    node = node2x("signatures", default_namespace="/rover1")
    ch = node["x"]
    assert ch.name == "rover1/x"
    calls = collections.defaultdict(list)

    def none():
        calls["none"].append(())

    def plain(m):
        calls["plain"].append(m)

    def with_source(m: int, source: pulicast.Address):
        calls["source"].append((m, source))

    def lead_first(m: int, lead: int, source: pulicast.Address):
        calls["lead_source"].append((m, lead, source))

    def as_str(m: str):
        calls["str"].append(m)

    def as_optional_str(m: Optional[str]):
        calls["optional_str"].append(m)

    class Holder:
        def on(self, message: Any):
            calls["method"].append(message)

    for cb in (none, plain, with_source, lead_first, as_str, as_optional_str, Holder().on):
        ch.subscribe(cb)
    assert ch.is_subscribed and not ch.is_published
    until_heard(ch, 7, calls["plain"])
    assert ch.is_published
    eventually("every int callback", lambda: calls["source"] and calls["lead_source"] and calls["method"])
    m, source = calls["source"][0]
    assert m == 7 and isinstance(source, pulicast.Address) and source.ip == "127.0.0.1"
    m, lead, _ = calls["lead_source"][0]
    assert (m, lead) == (7, 1)
    assert calls["none"], "a callback of no arguments hears every packet"
    assert calls["str"] == [], "an int is no str"
    eventually("None for a message that is no str", lambda: None in calls["optional_str"])
    assert calls["method"][0] == 7


def test_what_2x_refuses_is_refused(node2x):
    node = node2x("refusals")
    ch = node["y"]
    with pytest.raises(ValueError, match="Unsupported message type"):
        ch.subscribe(_list_callback)
    with pytest.raises(ValueError, match="lead"):
        ch.subscribe(_bad_lead)
    with pytest.raises(ValueError, match="source"):
        ch.subscribe(_bad_source)
    with pytest.raises(KeyError):
        ch << [1, 2]
    with pytest.raises(KeyError):
        ch << 1j


def _list_callback(m: list):
    pass


def _bad_lead(m: int, lead: str):
    pass


def _bad_source(m: int, source: str):
    pass


def test_a_handle_ends_its_subscription_when_unsubscribed_or_collected(node2x):
    node = node2x("handles")
    ch = node["z"]
    heard = []
    handle = ch.subscribe(lambda m: heard.append(m), with_handle=True)
    until_heard(ch, 1, heard)
    handle.unsubscribe()
    handle.unsubscribe()  # a second time does nothing
    assert not ch.is_subscribed
    heard.clear()
    ch << 2
    time.sleep(0.2)
    assert heard == []
    # Collected: the subscription ends with its handle.
    again = []
    ch.subscribe(lambda m: again.append(m), with_handle=True)
    gc.collect()
    assert not ch.is_subscribed
    # Without a handle it lasts as long as the channel.
    kept = []
    ch.subscribe(lambda m: kept.append(m))
    gc.collect()
    until_heard(ch, 3, kept)


def test_namespaces_resolve_as_2x_does(node2x):
    node = node2x("names", default_namespace="/robot")
    assert str(node) == "/robot"
    assert node["speed"].name == "robot/speed"
    assert node["/abs/x"].name == "abs/x"
    assert node["../../up"].name == "up"
    assert (node / "arm")["pose"].name == "robot/arm/pose"
    assert node.make_namespace("other")["x"].name == "other/x"
    assert node["speed"] is node["/robot/speed"], "one channel object per name"
    assert node.name == "names" and isinstance(node.session_id, int)
    assert set(c.name for c in node) >= {"robot/speed", "abs/x"}


def test_pause_holds_callbacks_back_and_resume_lets_them_run(node2x):
    node = node2x("pausing")
    other = node2x("talking")
    got = []
    node["numbers"].subscribe(lambda x: got.append(x))
    until_heard(other["numbers"], -1, got)
    node.pause_subscriptions()
    time.sleep(0.2)  # a callback running as it paused finishes
    got.clear()
    for i in range(10):
        other["numbers"] << i
    time.sleep(0.5)
    assert got == []  # held back
    node.resume_subscriptions()
    deadline = time.monotonic() + WAIT
    while len(got) < 10 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert got[-10:] == list(range(10))  # in order, none lost
    node.poll()  # nothing to do: callbacks run on their own threads
    started = time.monotonic()
    node.run_one()
    assert time.monotonic() - started >= 0.09  # one heartbeat period
    # A node stopped while paused lets its held-back callbacks go, uncalled.
    node.pause_subscriptions()
    received = node._native.stats()["messages_received"]
    other["numbers"] << 99
    eventually("99 held back", lambda: node._native.stats()["messages_received"] > received)
    node.stop()
    time.sleep(0.3)
    assert 99 not in got


def test_a_2x_trio_program_runs_on_pulicast_rs(node2x, port):
    import trio  # installed with the tests (.ci/run)
    from pulicast_rs.pulicast_trio import next_message_on, open_subscription

    talker = node2x("trio_talker")
    heard = []

    async def main():
        async with trio.open_nursery() as nursery:
            node = pulicast.TrioNode("trio_listener", nursery, port=port, interface_address="127.0.0.1")
            thread = threading.current_thread()
            on_trio_thread = []

            def on_number(x: int):
                on_trio_thread.append(threading.current_thread() is thread)

            node["numbers"].subscribe(on_number)
            async with open_subscription(node["chatter"], str) as messages:
                with trio.fail_after(WAIT):
                    while len(heard) < 3:
                        talker["chatter"] << "hi"
                        talker["numbers"] << 5
                        with trio.move_on_after(0.05):
                            heard.append(await messages.receive())
            assert heard[:3] == ["hi", "hi", "hi"]
            with trio.fail_after(WAIT):
                while not on_trio_thread:
                    talker["numbers"] << 5
                    await trio.sleep(0.02)
            assert all(on_trio_thread)  # callbacks run in Trio's thread
            with trio.fail_after(WAIT):
                async with trio.open_nursery() as inner:
                    inner.start_soon(lambda: _keep_sending(talker, trio))
                    assert await next_message_on(node["chatter"], str) == "hi"
                    inner.cancel_scope.cancel()
            later = trio.Event()
            node.run_later(0.01, later.set)
            with trio.fail_after(WAIT):
                await later.wait()
            node.stop()
            await node.stopped.wait()

    trio.run(main)


async def _keep_sending(talker, trio):
    while True:
        talker["chatter"] << "hi"
        await trio.sleep(0.02)


def test_a_trio_node_keeps_its_nursery_open_and_stops_with_it(node2x, port):
    import trio  # installed with the tests (.ci/run)

    talker = node2x("trio_talker2")
    heard = []
    nodes = []

    async def main():
        with trio.move_on_after(WAIT) as outer:
            async with trio.open_nursery() as nursery:
                # As a 2.x program does: make the node, subscribe, and let
                # the nursery run the node.
                node = pulicast.TrioNode("trio_keeper", nursery, port=port, interface_address="127.0.0.1")
                nodes.append(node)

                def on_chatter(text: str):
                    heard.append(text)
                    if len(heard) == 3:
                        nursery.cancel_scope.cancel()  # as a program that is done does

                node["chatter"].subscribe(on_chatter)

                async def talk():
                    while True:
                        talker["chatter"] << "hi"
                        await trio.sleep(0.02)

                nursery.start_soon(talk)
        assert not outer.cancelled_caught  # the nursery ended by the cancel, in time

    trio.run(main)
    assert heard[:3] == ["hi", "hi", "hi"]
    assert nodes[0]._native.stopped  # cancelling the nursery stopped the node

"""The native API on loopback: publish and receive each type, callbacks
that publish, raise or unsubscribe themselves, bad arguments, Ctrl-C out
of a blocking receive, and a node that stops under a waiting receiver."""

import os
import signal
import subprocess
import sys
import threading
import time

import pytest

import pulicast_rs
from conftest import WAIT, eventually


def send_until_received(channel, value, subscription):
    """Publishes `value` until the subscription gets a message (a new
    subscriber's group join takes a moment), at most WAIT seconds."""
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline:
        channel.publish(value)
        message = subscription.recv(timeout=0.05)
        if message is not None:
            # Copies sent while the first was on its way are no test's.
            while subscription.recv(timeout=0.2) is not None:
                pass
            return message
    pytest.fail(f"{value!r} never arrived on {channel.name}")


@pytest.mark.parametrize(
    "value, type_name",
    [
        (True, "boolean_msg"),
        (-42, "int64_msg"),
        (1.5, "double_msg"),
        ("Go LEFT!", "string_msg"),
        (b"\x00\xffraw", "bytes"),
        (bytearray(b"\x01\x02"), "bytes"),
    ],
)
def test_each_type_arrives_as_it_was_sent(make_node, value, type_name):
    talker = make_node("talker", "rover1")
    listener = make_node("listener")
    subscription = listener.channel("rover1/ctrl").subscribe()
    message = send_until_received(talker.channel("ctrl"), value, subscription)
    assert message.value == value
    assert type(message.value) is (bytes if isinstance(value, (bytes, bytearray)) else type(value))
    assert message.type_name == type_name
    assert message.channel == "rover1/ctrl"
    host, _, port = message.source.rpartition(":")
    assert host == "127.0.0.1" and int(port) > 0


def test_a_subscription_iterates_in_order_and_ends_when_closed(make_node):
    node = make_node("both")
    channel = node.channel("count")
    subscription = channel.subscribe()
    send_until_received(channel, -1, subscription)
    for i in range(100):
        channel.publish(i)
    got = [m.value for _, m in zip(range(100), subscription)]
    assert got == list(range(100))
    subscription.close()
    assert subscription.recv(timeout=0.1) is None


def test_callbacks_publish_raise_and_unsubscribe_themselves(make_node):
    node = make_node("callbacks")
    echoes = node.channel("echo").subscribe()
    seen = []

    def forward(message):
        seen.append(message.value)
        node.channel("echo").publish(message.value * 2)  # publishes from the callback

    def broken(message):
        raise RuntimeError("a bug in the program's callback")

    forwarding = node.channel("in").subscribe(forward)
    raising = node.channel("in").subscribe(broken)
    once = []

    def unsubscribe_self(message):
        once.append(message.value)
        holder[0].close()  # its own subscription, from inside the callback

    holder = [node.channel("in").subscribe(unsubscribe_self)]
    reply = send_until_received(node.channel("in"), 21, echoes)
    assert reply.value == 42
    # The raising callback raised for each message, and the node went on.
    eventually("the errors to be counted", lambda: raising.errors >= 1)
    node.channel("in").publish(5)
    assert echoes.recv(timeout=WAIT).value == 10
    assert len(once) == 1, "closed from inside its callback, it was called once"
    assert forwarding.errors == 0
    forwarding.close()
    raising.close()


def test_bad_arguments_raise_clear_errors_and_the_node_goes_on(make_node):
    node = make_node("careful")
    channel = node.channel("x")
    with pytest.raises(TypeError, match="can't publish a object"):
        channel.publish(object())
    with pytest.raises(TypeError, match="no member announces a native type"):
        channel.publish({"a": 1})
    with pytest.raises(TypeError, match="can't publish a set"):
        channel.publish({1, 2})
    with pytest.raises(OverflowError, match="64-bit"):
        channel.publish(2**70)
    with pytest.raises(ValueError):
        node.channel("")
    with pytest.raises(ValueError, match="läser"):
        node.channel("läser")  # names are ASCII, as 2.x groups are computed from them
    with pytest.raises(ValueError):
        node.channel("x" * 10_000)
    with pytest.raises(ValueError, match="IPv4"):
        pulicast_rs.Node("x", interface="localhost:1")
    with pytest.raises(ValueError, match="seconds"):
        channel.subscribe().recv(timeout=-1)
    with pytest.raises(TypeError, match="callable"):
        channel.subscribe(42)
    # Still works.
    subscription = channel.subscribe()
    assert send_until_received(channel, "fine", subscription).value == "fine"


def test_ctrl_c_interrupts_a_blocking_receive(make_node):
    node = make_node("waiting")
    subscription = node.channel("nothing_comes").subscribe()
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    started = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        subscription.recv()  # no timeout: only Ctrl-C ends it
    timer.join()
    assert time.monotonic() - started < WAIT


def test_a_node_stopped_by_another_thread_ends_the_iteration(make_node):
    node = make_node("stopping")
    subscription = node.channel("nothing_comes").subscribe()
    threading.Timer(0.3, node.stop).start()
    assert list(subscription) == []
    assert node.stopped
    with pytest.raises(pulicast_rs.PulicastError):
        node.channel("x").publish(1)


def test_threads_publish_and_receive_at_once(make_node):
    node = make_node("threads")
    channel = node.channel("t")
    subscription = channel.subscribe()
    send_until_received(channel, -1, subscription)
    per_thread = 100

    def publish(base):
        for i in range(per_thread):
            channel.publish(base + i)

    threads = [threading.Thread(target=publish, args=(k * 1000,)) for k in range(4)]
    for t in threads:
        t.start()
    got = set()
    deadline = time.monotonic() + WAIT
    while len(got) < 4 * per_thread and time.monotonic() < deadline:
        message = subscription.recv(timeout=0.2)
        if message is not None:
            got.add(message.value)
    for t in threads:
        t.join()
    assert got == {k * 1000 + i for k in range(4) for i in range(per_thread)}


def test_recv_many_takes_what_is_queued_in_one_call(make_node):
    node = make_node("many")
    channel = node.channel("burst")
    subscription = channel.subscribe()
    send_until_received(channel, -1, subscription)
    for i in range(50):
        channel.publish(i)
    got = []
    deadline = time.monotonic() + WAIT
    while len(got) < 50 and time.monotonic() < deadline:
        batch = subscription.recv_many(64, timeout=0.5)
        assert len(batch) <= 64
        got.extend(m.value for m in batch)
    assert got == list(range(50))
    assert subscription.recv_many(10, timeout=0.05) == []
    with pytest.raises(ValueError, match="at least 1"):
        subscription.recv_many(0)


def test_the_queue_capacity_and_the_receive_spin_are_set_on_the_node(make_node):
    with pytest.raises(ValueError, match="queue capacity"):
        make_node("no_queue", queue_capacity=0)
    with pytest.raises(ValueError, match="receive spin"):
        make_node("long_spin", receive_spin=0.01)  # above the 1 ms allowed
    with pytest.raises(ValueError, match="seconds"):
        make_node("negative_spin", receive_spin=-1)
    node = make_node("small_queue", queue_capacity=4, receive_spin=50e-6)
    channel = node.channel("burst")
    subscription = channel.subscribe()
    send_until_received(channel, -1, subscription)
    dropped = node.stats()["dropped_total"]
    for i in range(50):
        channel.publish(i)
    # All delivered meanwhile, and the queue keeps the newest 4.
    eventually("the oldest dropped", lambda: node.stats()["dropped_total"] - dropped >= 46)
    assert [m.value for m in subscription.recv_many(64, timeout=WAIT)] == [46, 47, 48, 49]


def test_batching_packs_messages_and_subscribers_read_them_singly(make_node):
    publisher, subscriber = make_node("batcher"), make_node("reader")
    channel = publisher.channel("imu")
    subscription = subscriber.channel("imu").subscribe()
    send_until_received(channel, -1, subscription)
    eventually("the reader known", lambda: "reader" in channel.subscribers())
    assert subscriber.channel("imu").wait_for_publisher(WAIT) == "batcher"
    with pytest.raises(ValueError):
        channel.enable_batching(0)
    with pytest.raises(ValueError):
        channel.enable_batching(5)  # above the 1 s allowed
    channel.enable_batching(0.5)
    before = subscriber.stats()
    for i in range(100):
        channel.publish(i)
    channel.flush()  # else within 0.5 s
    got = []
    deadline = time.monotonic() + WAIT
    while len(got) < 100 and time.monotonic() < deadline:
        got.extend(m.value for m in subscription.recv_many(256, timeout=0.5))
    assert got == list(range(100))
    after = subscriber.stats()
    assert after["messages_received"] - before["messages_received"] >= 100
    # A few datagrams (and discovery's), not a hundred.
    assert after["datagrams_received"] - before["datagrams_received"] < 30
    channel.disable_batching()
    channel.publish(7)
    assert subscription.recv(timeout=WAIT).value == 7
    with pytest.raises(pulicast_rs.PulicastError, match="[Tt]ime"):
        subscriber.channel("nobody/publishes").wait_for_publisher(0.2)


def test_stats_and_members_show_the_node_and_the_fleet(make_node):
    talker = make_node("stats_talker", "rover1", config="alice")
    listener = make_node("stats_listener")
    subscription = listener.channel("rover1/pose").subscribe()
    send_until_received(talker.channel("pose"), 1.0, subscription)
    stats = listener.stats()
    assert stats["messages_delivered"] >= 1 and stats["datagrams_received"] >= 1
    assert stats["dropped_total"] == sum(stats["dropped"].values())
    assert "wrong_type" in stats["dropped"] or len(stats["dropped"]) > 5
    assert talker.stats()["messages_sent"] >= 1

    def talker_seen():
        return [m for m in listener.members() if m["name"] == "stats_talker"]

    eventually("the talker in the listener's fleet", lambda: talker_seen() and "rover1/pose" in talker_seen()[0]["publishes"])
    seen = talker_seen()[0]
    assert (seen["namespace"], seen["config"], seen["state"], seen["compat"]) == ("rover1", "alice", "alive", False)
    assert seen["key"] == talker.session_id
    assert all(m["name"] != "stats_listener" for m in listener.members()), "the others only"


def test_a_sealed_namespace_is_read_only_with_its_key(make_node):
    key = "ab" * 32
    sealer = make_node("sealer", "rover1", keys=f"rover1={key}")
    keyed = make_node("keyed", keys=f"rover1={key}")
    keyless = make_node("keyless")
    with_key = keyed.channel("rover1/secret").subscribe()
    without_key = keyless.channel("rover1/secret").subscribe()
    assert send_until_received(sealer.channel("secret"), "for keys only", with_key).value == "for keys only"
    assert without_key.recv(timeout=0.3) is None
    eventually("the keyless node to count what it could not open", lambda: keyless.stats()["dropped_total"] >= 1)
    with pytest.raises(ValueError, match="keys"):
        make_node("bad", keys="rover1=0123")
    try:
        make_node("bad2", keys=f"rover1={key[:-2]}zz")
    except ValueError as e:
        assert key[:-2] not in str(e), "a key never shows in an error"


def test_floats_that_are_no_numbers_stay_floats(make_node):
    import math

    node = make_node("floats")
    channel = node.channel("f")
    subscription = channel.subscribe()
    send_until_received(channel, 0.0, subscription)
    for value in (float("nan"), float("inf"), -float("inf")):
        channel.publish(value)
        got = subscription.recv(timeout=WAIT).value
        assert type(got) is float
        assert math.isnan(got) if math.isnan(value) else got == value


def test_a_callback_closes_a_subscription_this_thread_waits_on(make_node):
    # The thread waiting in recv drives the node, so the callback runs on
    # it: closing the subscription it waits on must not deadlock.
    node = make_node("closer")
    data = node.channel("data").subscribe()
    closing = node.channel("ctrl").subscribe(lambda m: data.close())
    done = threading.Event()

    def iterate():
        for _ in data:
            pass
        done.set()

    waiter = threading.Thread(target=iterate, daemon=True)
    waiter.start()
    deadline = time.monotonic() + WAIT
    while not done.is_set() and time.monotonic() < deadline:
        node.channel("ctrl").publish(1)
        done.wait(0.05)
    assert done.is_set(), "the iteration never ended: a deadlock"
    closing.close()


def test_extreme_arguments_are_no_crash(make_node):
    node = make_node("a\x00b")  # a NUL in a node's name
    assert node.name == "a\x00b"
    subscription = node.channel("x").subscribe()
    threading.Timer(0.3, subscription.close).start()
    assert subscription.recv(timeout=1e19) is None  # beyond what the clock holds: forever


def test_a_program_that_exits_without_stopping_its_node_exits_cleanly(tmp_path, port):
    # Callbacks busy as the interpreter exits: none may take the GIL while
    # it finalizes (that aborts the process).
    script = tmp_path / "exits.py"
    script.write_text(
        "import time, pulicast_rs\n"
        f"a = pulicast_rs.Node('a', port={port}, interface='127.0.0.1', keys_from_env=False)\n"
        f"b = pulicast_rs.Node('b', port={port}, interface='127.0.0.1', keys_from_env=False)\n"
        "got = []\n"
        "s = b.channel('x').subscribe(lambda m: (got.append(m.value), time.sleep(0.005)))\n"
        "for i in range(300):\n"
        "    a.channel('x').publish(i)\n"
        "time.sleep(0.05)\n"
        "print(len(got) > 0)\n"
    )
    for _ in range(3):
        done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        assert done.stdout.strip() == "True"


def test_dicts_are_published_as_the_native_type_a_rust_member_announces(make_node, port):
    """The demo rover subscribes `rover1/ctrl` as its Rust `Twist`: a dict
    published there drives it, and its `Pose` comes back as a dict."""
    from test_settings import net, rust_bin

    node = make_node("py_driver")
    ctrl = node.channel("rover1/ctrl")
    with pytest.raises(TypeError, match="no member announces a native type"):
        node.channel("nobody/typed").publish({"linear": 1.0})
    rover = subprocess.Popen(
        [str(rust_bin("examples/rover_demo")), "--role", "rover", "--name", "rover1", "--secs", "30", *net(port)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        poses = node.channel("rover1/pose").subscribe()
        # Read as bytes until discovery brings the rover's type, then as a
        # dict of the fields of its `Pose`.
        first = poses.recv(timeout=10)
        deadline = time.monotonic() + WAIT
        while first is not None and first.type_name != "Pose" and time.monotonic() < deadline:
            first = poses.recv(timeout=1)
        assert first is not None and first.type_name == "Pose", first
        start_x = first.value["x"]
        with pytest.raises(ValueError, match="angular"):
            ctrl.publish({"linear": 0.5})
        with pytest.raises(ValueError, match="linear"):
            ctrl.publish({"linear": "fast", "angular": 0.0})
        deadline = time.monotonic() + WAIT
        moved = False
        while time.monotonic() < deadline and not moved:
            ctrl.publish({"linear": 0.5, "angular": 0.0})
            message = poses.recv(timeout=0.2)
            moved = message is not None and message.value["x"] > start_x + 0.05
        assert moved, "the rover never drove on the dicts"
    finally:
        rover.kill()
        rover.wait()


def test_the_type_stubs_name_every_public_method():
    """Editors complete from `_native.pyi`: it names every public attribute
    of every class of the native module (a base's count for its
    subclasses)."""
    import ast
    import inspect
    from pathlib import Path

    from pulicast_rs import _native

    stub = ast.parse((Path(_native.__file__).parent / "_native.pyi").read_text())
    declared = {}
    bases = {}
    for node in stub.body:
        if isinstance(node, ast.ClassDef):
            names = set()
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    names.add(item.name)
                elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                    names.add(item.target.id)
            declared[node.name] = names
            bases[node.name] = [b.id for b in node.bases if isinstance(b, ast.Name)]

    def in_stub(cls, name):
        return name in declared.get(cls, set()) or any(in_stub(b, name) for b in bases.get(cls, []))

    missing = []
    for cls_name, cls in inspect.getmembers(_native, inspect.isclass):
        if issubclass(cls, BaseException):
            continue
        assert cls_name in declared, f"{cls_name} has no stub"
        for name in dir(cls):
            if not name.startswith("_") and not in_stub(cls_name, name):
                missing.append(f"{cls_name}.{name}")
    assert not missing, missing

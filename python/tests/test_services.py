"""Services from Python: serving a function, calling servers of any
language, progress, cancel, call_all, `name@node`, the nearest server, and
Python and Rust calling each other."""

import subprocess
import threading
import time

import pytest

import pulicast_rs
from conftest import WAIT, eventually
from test_settings import net, rust_bin


def test_a_python_server_answers_python_calls(make_node):
    server_node = make_node("py_server", "rover1")

    @server_node.serve("double")
    def double(x: int) -> int:
        if x < 0:
            raise ValueError("negative")
        return 2 * x

    assert isinstance(double, pulicast_rs.Server) and double.service == "rover1/double"
    shout = server_node.serve("shout", lambda s: s.upper() + "!", request=str, reply=str)
    half = server_node.serve("half", lambda x: x / 2, request=float, reply=float)

    caller = make_node("py_caller")
    client = caller.client("rover1/double")
    assert client.call(21) == 42
    assert client.servers() == ["py_server"]
    assert caller.client("rover1/shout").call("go") == "GO!"
    assert caller.client("rover1/half").call(3) == 1.5  # an int is a float here
    # The handler's exception is the caller's failure, in its words.
    with pytest.raises(pulicast_rs.PulicastError, match="ValueError: negative"):
        client.call(-1)
    # A request that fits no type is refused before anything is sent.
    with pytest.raises(TypeError, match="int64_msg, not str"):
        client.call("twelve")
    with pytest.raises(OverflowError):
        client.call(2**70)
    # And the server goes on.
    assert client.call(5) == 10
    with pytest.raises(pulicast_rs.PulicastError, match="no server of nobody"):
        caller.client("nobody", timeout=0.3).call(1)
    # Raw bytes take bytes-like objects only (bytes(5) would be five zeros).
    echo = server_node.serve("echo", lambda b: bytes(b[::-1]), request=bytes, reply=bytes)
    raw = caller.client("rover1/echo")
    assert raw.call(b"abc") == b"cba" and raw.call(memoryview(b"xy")) == b"yx"
    with pytest.raises(TypeError, match="bytes"):
        raw.call(5)
    looped = []
    looped.append(looped)
    with pytest.raises(ValueError, match="deeper"):
        caller.fleet_settings().set("rover1/anything", looped, timeout=0.1)
    assert client.call(1, timeout=1e19) == 2
    with pytest.raises(TypeError, match="progress"):
        server_node.serve("p", lambda x, call: x, request=int, reply=int, progress=bytes)
    echo.close()
    shout.close()
    half.close()


def test_bad_servers_are_refused_with_clear_errors(make_node):
    node = make_node("py_server")
    with pytest.raises(TypeError, match="not known: annotate"):
        node.serve("a", lambda x: x)
    with pytest.raises(TypeError, match="not 3 arguments"):
        node.serve("b", lambda x, y, z: x, request=int, reply=int)
    with pytest.raises(TypeError, match="bool, int, float, str or bytes"):
        node.serve("c", lambda x: x, request=list, reply=int)
    with pytest.raises(TypeError, match="callable"):
        node.serve("d", 3, request=int, reply=int)
    with pytest.raises(ValueError):
        node.serve("bad\x00name", lambda x: x, request=int, reply=int)
    keep = node.serve("e", lambda x: x, request=int, reply=int)
    with pytest.raises(ValueError, match="already serves"):
        node.serve("e", lambda x: x, request=int, reply=int)
    keep.close()


def test_progress_cancel_call_all_and_targets(make_node):
    a = make_node("server_a", "rover1")
    b = make_node("server_b", "rover1")
    cancelled = threading.Event()

    def count(n: int, call) -> str:
        for i in range(n):
            if call.cancelled:
                cancelled.set()
                return "stopped"
            call.progress(i)
            time.sleep(0.02)
        return f"counted {n} at {call.caller is not None}"

    counters = [node.serve("count", count, progress=int) for node in (a, b)]
    whoami = [node.serve("whoami", (lambda name: lambda _: name)(node.name), request=int, reply=str) for node in (a, b)]
    caller = make_node("caller")
    counting = caller.client("rover1/count")
    eventually("both servers", lambda: len(counting.servers()) == 2)

    call = counting.start(4)
    assert call.node in ("server_a", "server_b")
    assert list(call) == [0, 1, 2, 3]
    assert call.reply() == "counted 4 at True"
    with pytest.raises(pulicast_rs.PulicastError, match="taken already"):
        call.reply()

    # Cancelled mid-way: the handler is told and stops.
    long = counting.start(500, timeout=20)
    assert long.progress() == 0
    long.cancel()
    assert cancelled.wait(WAIT)
    with pytest.raises(pulicast_rs.PulicastError):
        long.reply()

    runs = []
    counted = [node.serve("counted", (lambda name: lambda x: runs.append(name) or x)(node.name), request=int, reply=int) for node in (a, b)]
    counted_client = caller.client("rover1/counted")
    eventually("both counted servers", lambda: len(counted_client.servers()) == 2)
    answers = counted_client.call_all(7)
    assert sorted(answers) == [("server_a", 7, None), ("server_b", 7, None)]
    assert sorted(runs) == ["server_a", "server_b"], "each server ran the call once"

    # cancel() from another thread ends a wait for progress at once.
    waiting = counting.start(500, timeout=20)
    assert waiting.progress() == 0
    woke = []
    waiter = threading.Thread(target=lambda: woke.append(list(waiting)))
    waiter.start()
    time.sleep(0.1)
    started = time.monotonic()
    waiting.cancel()
    waiter.join(WAIT)
    assert not waiter.is_alive() and time.monotonic() - started < WAIT

    whoami_client = caller.client("rover1/whoami")
    eventually("both whoami servers", lambda: len(whoami_client.servers()) == 2)
    answers = whoami_client.call_all(0)
    assert sorted((node, reply, error) for node, reply, error in answers) == [
        ("server_a", "server_a", None),
        ("server_b", "server_b", None),
    ]
    assert caller.client("rover1/whoami@server_b").call(0) == "server_b"
    nearest = caller.ns("rover1").client("whoami").nearest()
    assert nearest.call(0) in ("server_a", "server_b")
    # A progress value of the wrong type is the handler's error.
    bad = a.serve("bad_progress", lambda n, call: call.progress("x"), request=int, reply=int, progress=int)
    with pytest.raises(pulicast_rs.PulicastError, match="TypeError"):
        caller.client("rover1/bad_progress@server_a").call(1)
    for s in counters + whoami + counted + [bad]:
        s.close()


def test_a_callback_calls_a_service_and_a_handler_calls_another(make_node):
    """Callbacks run off the node's receive path, so a callback that waits
    for a reply (which that path brings) does not deadlock; nor does a
    handler that calls another service."""
    node = make_node("py_node")
    inner = node.serve("inner", lambda x: x + 1, request=int, reply=int)
    client = node.client("inner")
    outer = node.serve("outer", lambda x: 10 * client.call(x), request=int, reply=int)
    other = make_node("other")
    got = []
    subscription = node.channel("trigger").subscribe(lambda m: got.append(node.client("outer").call(m.value)))
    eventually("the subscription known", lambda: "py_node" in [m["name"] for m in other.members()])
    time.sleep(0.2)
    other.channel("trigger").publish(4)
    eventually("the callback's call", lambda: got == [50])
    subscription.close()
    inner.close()
    outer.close()


def test_rust_calls_a_python_server_and_python_calls_rust_servers(make_node, port):
    node = make_node("py_server", "pyrover")
    double = node.serve("double", lambda x: 2 * x, request=int, reply=int)
    puli = rust_bin("puli")
    out = subprocess.run(
        [str(puli), "call", "pyrover/double", "21", "--timeout", "10", *net(port)],
        capture_output=True, text=True, timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "42"

    server = subprocess.Popen(
        [str(puli), "serve", "--name", "rust_server", "--for", "30", "--step-ms", "5", *net(port)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert server.stderr.readline().startswith("READY"), "puli serve never got ready"
        caller = make_node("py_caller")
        assert caller.client("double", timeout=10).call(21) == 42
        assert caller.client("echo").call("hello") == "hello"
        # A Rust native type, written and read as dicts and lists.
        plan = caller.client("plan").call({"goal": [4.0, 1.0], "steps": 2})
        assert plan == {"points": [[0.0, 1.0], [2.0, 1.0]], "by": "rust_server"}
        with pytest.raises(ValueError, match="steps"):
            caller.client("plan").call({"goal": [4.0, 1.0]})
        with pytest.raises(ValueError, match="goal"):
            caller.client("plan").call({"goal": "north", "steps": 2})
        with pytest.raises(pulicast_rs.PulicastError, match="too many"):
            caller.client("plan").call({"goal": [1.0, 1.0], "steps": 20000})
        call = caller.client("count").start(3)
        assert list(call) == [0, 1, 2]
        assert call.reply() == "counted 3"
    finally:
        server.kill()
        server.wait()
        double.close()

"""The 2.x reference package's side of `python -m pulicast_rs.bench`, run
by the reference package's interpreter (it never imports pulicast_rs).

    python _bench2x.py pub  PORT SIZE SECS      -> {"sent": N}
    python _bench2x.py recv PORT SECS           -> {"received": N, "first": T, "last": T}
    python _bench2x.py pong PORT                -> echoes bench/ping to bench/pong
    python _bench2x.py ping PORT SIZE ROUNDS    -> {"rtt_us": [...]}

Every node is on loopback (interface 127.0.0.1, TTL 0); every loop ends
by its count or time.
"""

import json
import sys
import threading
import time
import types

# The package's __init__ imports its Qt node (PySide2, not installed).
_qt = types.ModuleType("pulicast.pulicast_qt")
_qt.QtNode = object
sys.modules.setdefault("pulicast.pulicast_qt", _qt)

import pulicast  # noqa: E402


def node(port, name):
    return pulicast.ThreadedNode(name, port=port, ttl=0, interface_address="127.0.0.1")


def main():
    role, port = sys.argv[1], int(sys.argv[2])
    if role == "pub":
        size, secs = int(sys.argv[3]), float(sys.argv[4])
        n = node(port, "bench_pub_2x")
        channel = n["bench/thr"]
        payload = bytes(size)
        time.sleep(0.5)  # the subscriber joins
        sent, end = 0, time.monotonic() + secs
        while time.monotonic() < end:
            channel.publish(payload)
            sent += 1
        print(json.dumps({"sent": sent}), flush=True)
    elif role == "recv":
        secs = float(sys.argv[3])
        n = node(port, "bench_sub_2x")
        got = {"received": 0, "first": None, "last": None}

        def on(_: bytes):
            now = time.monotonic()
            if got["first"] is None:
                got["first"] = now
            got["last"] = now
            got["received"] += 1

        n["bench/thr"].subscribe(on)
        n.start()
        print("READY", flush=True)
        time.sleep(secs)
        n.stop()
        print(json.dumps(got), flush=True)
    elif role == "pong":
        n = node(port, "bench_pong_2x")
        pong = n["bench/pong"]

        def on_ping(m: bytes):  # raw: 2.x drops what it can't decode otherwise
            pong.publish(bytes(m))

        n["bench/ping"].subscribe(on_ping)
        n.start()
        print("READY", flush=True)
        time.sleep(120)
        n.stop()
    elif role == "ping":
        size, rounds = int(sys.argv[3]), int(sys.argv[4])
        n = node(port, "bench_ping_2x")
        answered = threading.Event()

        def on_pong(m: bytes):
            answered.set()

        n["bench/pong"].subscribe(on_pong)
        n.start()
        ping = n["bench/ping"]
        payload = bytes(size)
        rtts = []
        time.sleep(0.5)
        give_up = time.monotonic() + 60
        for _ in range(rounds):
            if time.monotonic() > give_up:
                break
            answered.clear()
            start = time.perf_counter()
            ping.publish(payload)
            if answered.wait(0.2):
                rtts.append((time.perf_counter() - start) * 1e6)
        n.stop()
        print(json.dumps({"rtt_us": rtts}), flush=True)


if __name__ == "__main__":
    main()

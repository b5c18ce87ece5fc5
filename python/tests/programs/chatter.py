"""A Pulicast 2.x program, as a 2.x user writes it: the interop test runs it
on the reference package and, with only its import line changed, on
pulicast_rs, and has the two talk to each other.

    chatter.py talker PORT      publishes ints, floats, texts, flags, raw bytes and Vec2s
    chatter.py listener PORT    prints one JSON line per message it receives by type
"""

import pulicast

import json
import struct
import sys
import threading
import time
from typing import Optional


class Vec2:
    """A ZCM class of the shape zcm-gen makes (encode, static decode, packed
    fingerprint), written out so the program needs no generated package."""

    __slots__ = ("x", "y")
    _FINGERPRINT = b"VEC2TEST"

    def __init__(self):
        self.x = 0.0
        self.y = 0.0

    def encode(self):
        return self._FINGERPRINT + struct.pack(">dd", self.x, self.y)

    @staticmethod
    def decode(data):
        data = bytes(data)
        if data[:8] != Vec2._FINGERPRINT:
            raise ValueError("Decode error")
        v = Vec2()
        v.x, v.y = struct.unpack(">dd", data[8:24])
        return v

    @staticmethod
    def _get_packed_fingerprint():
        return Vec2._FINGERPRINT


pulicast.serialization.register_zcm_type(Vec2)


def talker(node, count):
    node.start()
    for i in range(count):
        node["ints"] << i
        node["floats"] << i + 0.5
        node["texts"] << f"hi {i}"
        node["flags"] << (i % 2 == 0)
        node["raw"] << bytes([i % 256, 0xFF])
        v = Vec2()
        v.x, v.y = float(i), float(-i)
        node["vecs"] << v
        time.sleep(0.02)
    node.stop()


def listener(node, seconds):
    lock = threading.Lock()

    def report(channel, value, **extra):
        with lock:
            print(json.dumps({"channel": channel, "value": value, **extra}), flush=True)

    def on_int(message: int, source: pulicast.Address, lead: int):
        report("ints", message, lead=lead, port=source.port)

    def on_float(message: float):
        report("floats", message)

    def on_text(message: str, lead: int):
        report("texts", message)

    def on_flag(message: bool):
        report("flags", message)

    def on_raw(message: bytes):
        report("raw", bytes(message).hex())

    def on_vec(message: Vec2):
        report("vecs", [message.x, message.y])

    def on_any(message):
        kind = type(message).__name__
        report("vecs_any", kind)

    def on_text_as_int(message: Optional[int]):
        # A text is no int: None, as the annotation asks.
        report("texts_as_int", message)

    node["ints"].subscribe(on_int)
    node["floats"].subscribe(on_float)
    node["texts"].subscribe_ordered(on_text)
    node["flags"].subscribe(on_flag)
    node["raw"].subscribe(on_raw)
    node["vecs"].subscribe(on_vec)
    node["vecs"].subscribe(on_any)
    node["texts"].subscribe(on_text_as_int)
    node.start()
    print("READY", file=sys.stderr, flush=True)
    time.sleep(seconds)
    node.stop()


if __name__ == "__main__":
    role, port = sys.argv[1], int(sys.argv[2])
    node = pulicast.ThreadedNode(role, port=port, interface_address="127.0.0.1")
    if role == "talker":
        talker(node, int(sys.argv[3]) if len(sys.argv) > 3 else 100)
    else:
        listener(node, float(sys.argv[3]) if len(sys.argv) > 3 else 5.0)

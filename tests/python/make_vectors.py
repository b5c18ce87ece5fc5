#!/usr/bin/env python3
"""Regenerate the Pulicast 2.x test vectors from the reference package pulicast==2.0.1.

Usage (from the repository root, with the venv made by tests/python/setup_venv.sh):

    target/pyvenv/bin/python tests/python/make_vectors.py pulicast-rs/tests/vectors/pulicast2.json

Without an argument the JSON goes to stdout. Every value is obtained by calling the
reference package (GPLv3: it is called here, none of its code is copied). The few
values it only has inline in a method body are measured from that method; the
comments say which.
"""
import inspect
import ipaddress
import json
import sys
import time
import types
from unittest import mock

# The package's __init__ imports its Qt node (PySide2, not installable here).
_qt = types.ModuleType("pulicast.pulicast_qt")
_qt.QtNode = object
sys.modules.setdefault("pulicast.pulicast_qt", _qt)

import pulicast  # noqa: E402
import pulicast_messages  # noqa: E402
from pulicast import Address, Channel, ThreadedNode, TrioNode  # noqa: E402
from pulicast.core.transport import Transport  # noqa: E402
from pulicast.core.utils.name_resolution import resolve_name  # noqa: E402
from pulicast.discovery.node_view import NodeView  # noqa: E402
from pulicast.node import Node  # noqa: E402
from pulicast.serialization import get_message_encoder, is_zcm_type  # noqa: E402
from pulicast.transport.udp_transport import (  # noqa: E402
    MAX_UDP_PACKET_SIZE, UDPChannelSender, multicast_group_for_channel, sdbm)
from pulicast_messages import (  # noqa: E402
    boolean_msg, byte_msg, double_msg, float_msg, int8_msg, int16_msg, int32_msg, int64_msg,
    pulicast_channel, pulicast_node, string_msg)


class CaptureTransport(Transport):
    """A Transport whose senders keep each datagram the reference's UDPChannelSender
    builds (header + channel name + what the Channel passed down) instead of sending it."""

    def __init__(self):
        self.datagrams = []

    def make_channel_sender(self, channel_name):
        sender = UDPChannelSender(channel_name)
        sender.send_to_socket = lambda data: self.datagrams.append(bytes(data))
        return sender

    def start_receiving_messages_for(self, channel_name, packet_callback):
        pass


def zcm(cls, **fields):
    msg = cls()
    for name, value in fields.items():
        setattr(msg, name, value)
    return msg


def channel_info(name, publishing_period_ns, is_published, is_subscribed):
    return zcm(pulicast_channel, name=name, publishing_period_ns=publishing_period_ns,
               is_published=is_published, is_subscribed=is_subscribed)


def send(channel_name, payload, seq=0):
    """The datagram a reference Channel emits for `channel << payload` as its message number `seq`."""
    transport = CaptureTransport()
    channel = Channel(channel_name, transport)
    # The Channel keeps its next sequence number in a private counter (starts at 0).
    channel._sequence_numbered_sender._seq_no = seq
    channel << payload
    return transport.datagrams[-1].hex()


def fingerprints():
    # The members the reference itself registers (serialization.register_zcm_package), by name.
    return {name: t._get_packed_fingerprint().hex()
            for name, t in inspect.getmembers(pulicast_messages) if is_zcm_type(t)}


def message_encodings():
    out = {}
    for cls, value in [(string_msg, "Go LEFT!"), (int64_msg, -42), (double_msg, 3.5),
                       (boolean_msg, True), (int32_msg, 7), (float_msg, 1.25), (int8_msg, -1),
                       (int16_msg, 300), (byte_msg, 255)]:
        out[f"{cls.__name__}({value!r})"] = zcm(cls, value=value).encode().hex()
        if cls in (string_msg, int64_msg, double_msg, boolean_msg):  # what `channel << value` uses
            assert get_message_encoder(type(value))(value).hex() == out[f"{cls.__name__}({value!r})"]
    node = zcm(pulicast_node, name="rover_controller", session_id=-4967202353444692722, num_channels=2,
               channels=[channel_info("__nodes", 100_000_000, True, False),
                         channel_info("rover1/ctrl", 0, False, True)])
    out["pulicast_node(name='rover_controller', session_id=-4967202353444692722, "
        "channels=[__nodes pub 100ms, rover1/ctrl sub])"] = node.encode().hex()
    return out


def packets():
    return {
        "channel 'rover1/ctrl', seq 0, string_msg('Go LEFT!')": send("rover1/ctrl", "Go LEFT!"),
        "channel 'a', seq 4294967295, raw bytes 010203": send("a", bytes.fromhex("010203"), 2**32 - 1),
    }


def multicast_groups():
    names = ["__nodes", "rover1/ctrl", "rover1/left_arm/pose", "ctrl", "a", "drivers/rover2/arm/attitude"]
    return {name: multicast_group_for_channel(name) for name in names}


def name_resolution():
    cases = [("rover1/left_arm/", "ctrl"), ("rover1/left_arm/", "../ctrl"), ("rover1/left_arm/", "/ctrl"),
             ("/", "ctrl"), ("/", "rover1/ctrl"), ("rover1", "ctrl"), ("rover1", "left_arm/pose"),
             ("rover1", "/rover2/pose"), ("rover1", "../rover2/pose"), ("/rover1/", "./ctrl"),
             ("", "ctrl"), ("a/b/c", "../../x"), ("a", "x//y"), ("a/b", "../../../x")]
    return [{"namespace": ns, "name": name, "resolved": resolve_name(name, ns)} for ns, name in cases]


def defaults():
    node_args = inspect.signature(ThreadedNode.__init__).parameters
    trio_args = inspect.signature(TrioNode.__init__).parameters
    for arg in ("port", "ttl", "heartbeat_period"):
        assert node_args[arg].default == trio_args[arg].default, arg

    # The channel a reference Node heartbeats on (a literal inside Node.__init__).
    discovery_channel = Node("probe", "/", 0.1, CaptureTransport())._nodes_channel.name

    # NodeView sets a node's deadline to "now + heartbeat_period * N" inline. Measure N:
    # a node heartbeating every 1 s, seen with the clock stopped at 0.
    info = zcm(pulicast_node, name="probe", channels=[channel_info(discovery_channel, 10**9, True, False)])
    with mock.patch.object(time, "time", return_value=0.0):
        dead_after = NodeView(info, Address("127.0.0.1", 0)).deadline
    assert dead_after == int(dead_after)

    # The group base and hash are inline in multicast_group_for_channel: the base is the
    # group of the empty name (sdbm("") == 0); the hash description is spelled out here and
    # checked against the reference's own sdbm for every name in multicast_groups.
    group_base = multicast_group_for_channel("")
    for name, group in multicast_groups().items():
        offset = int(ipaddress.IPv4Address(group)) - int(ipaddress.IPv4Address(group_base))
        assert offset == sdbm(name) % 2**23, name

    return {
        "port": pulicast.DEFAULT_PORT,
        "ttl": node_args["ttl"].default,
        "heartbeat_period_s": node_args["heartbeat_period"].default,
        "node_dead_after_missed_heartbeats": int(dead_after),
        "discovery_channel": discovery_channel,
        "group_base": group_base,
        "group_hash": "sdbm(name) mod 2^23",
        "max_udp_payload": MAX_UDP_PACKET_SIZE,
    }


def settings():
    """What a reference `Setting` (pulicast_tools.puliconf) sends, and how puliconf names things."""
    from pulicast_messages import poke_setting, reset_setting_to_default, unset_setting
    from pulicast_tools.puliconf import channel_naming_conventions as names
    from pulicast_tools.puliconf.setting import Setting, accept_range

    def confirmation(make):
        """The payload of the confirmation a new setting publishes (after the packet header)."""
        transport = CaptureTransport()
        node = Node("probe", "/", 0.1, transport)
        setting = make(node / "rover1")
        datagram = transport.datagrams[-1]
        name_len = datagram[4]
        channel = datagram[5:5 + name_len].decode()
        assert channel == "rover1/.config/" + setting.name.split("/", 1)[1], channel
        return {"channel": channel, "payload": datagram[5 + name_len + 4:].hex()}

    return {
        "confirmations": {
            "max_speed = 1.5 (double), validator accept_range(0.0, 2.0), as created":
                confirmation(lambda ns: Setting("max_speed", ns, initial_value=1.5,
                                                validate_roc=accept_range(0.0, 2.0))),
            "mode: str, unset, as created": confirmation(lambda ns: Setting("mode", ns, value_type=str)),
            "arm/gain = 3 (int), as created": confirmation(lambda ns: Setting("arm/gain", ns, initial_value=3)),
        },
        "requests": {
            "poke_setting": zcm(poke_setting).encode().hex(),
            "unset_setting": zcm(unset_setting).encode().hex(),
            "reset_setting_to_default": zcm(reset_setting_to_default).encode().hex(),
        },
        "names": [
            {"channel": c,
             "is_confirmation": names.is_setting_confirmation_channel(c),
             "is_request": names.is_setting_roc_channel(c),
             "setting": (names.deduce_setting_name_from_confirmation_channel(c)
                         if names.is_setting_confirmation_channel(c) else None)}
            for c in ["rover1/.config/max_speed", "rover1/.config/max_speed.r", "rover1/.config/arm/gain",
                      ".config/gain", "rover1/pose"]
        ],
    }


def main():
    vectors = {
        "_about": "Test vectors for the Pulicast 2.x wire format, computed with the reference Python "
                  "package pulicast==2.0.1 (PyPI). All byte strings are hex.",
        "fingerprints": fingerprints(),
        "message_encodings": message_encodings(),
        "packets": packets(),
        "multicast_groups": multicast_groups(),
        "name_resolution": name_resolution(),
        "defaults": defaults(),
        "settings": settings(),
    }
    text = json.dumps(vectors, indent=1)  # no trailing newline, like the original file
    if len(sys.argv) > 1:
        with open(sys.argv[1], "w") as f:
            f.write(text)
    else:
        sys.stdout.write(text)


if __name__ == "__main__":
    main()

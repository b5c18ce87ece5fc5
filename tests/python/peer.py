#!/usr/bin/env python3
"""Pulicast 2.x reference test peer (drives the PyPI package pulicast==2.0.1).

Run it with the venv that tests/python/setup_venv.sh makes. All traffic is pinned
to loopback: interface 127.0.0.1, TTL 0 (unless --defaults, for tests inside a
network namespace of their own).

    peer.py publish   --port P --name NODE --channel CH --kind KIND --value V
                      [--count N] [--period S] [--linger S] [--heartbeat S]
    peer.py subscribe --port P --name NODE --channel CH [--count N] [--timeout S]
                      [--as auto|any|bytes|str|int|float|bool] [--ordered]
    peer.py nodes     --port P --name NODE [--for S]

publish: KIND is str, int, float, bool, bytes (value as hex) or none (empty
    payload), which go through the package's own encoders (`channel << value`),
    or the name of a ZCM primitive message of the package (int8_msg, int16_msg,
    int32_msg, int64_msg, float_msg, double_msg, string_msg, boolean_msg,
    byte_msg) to publish that message explicitly. A "{i}" in --value is replaced
    by the message index (str.format, so "{i:02x}" works for hex bytes).
    Prints one JSON line {"published": N, "session_id": ...} when done sending.

subscribe: one JSON line per message on stdout:
    {"channel", "value", "type", "lead", "source", "raw"}
    value is the decoded value (bytes as hex; ZCM structs as dicts), type the
    Python type name, lead the lead the package computed, source "ip:port" of the
    sending socket, raw the payload hex (only with --as auto).
    --as auto  (default) subscribes for raw bytes and decodes with the package's
               universal decoder; payloads it can't decode are reported as bytes
               (decode errors as type "decode_error").
    --as any   uses the package's own untyped subscription (drops unknown
               fingerprints, exactly like a 2.x user callback without annotation).
    --as str|int|float|bool|bytes uses a subscription annotated with that type.
    Exit status 0 after --count messages, 1 on timeout with fewer.

nodes: runs NodeDiscoverer for --for seconds, prints a JSON array of every node
    seen (alive ones and ones that died during the window).

Every subcommand writes "READY {json}" to stderr once its node runs (and, for
subscribe, once the subscription is in place).
"""
import argparse
import json
import queue
import sys
import threading
import time
import types
import typing
from typing import Any, Optional

# The package's __init__ imports its Qt node (PySide2, not installable here).
_qt = types.ModuleType("pulicast.pulicast_qt")
_qt.QtNode = object
sys.modules.setdefault("pulicast.pulicast_qt", _qt)

import pulicast  # noqa: E402
import pulicast_messages  # noqa: E402
from pulicast.address import Address  # noqa: E402
from pulicast.discovery.node_discoverer import NodeDiscoverer  # noqa: E402
from pulicast.serialization import get_message_decoder  # noqa: E402

LOOPBACK = "127.0.0.1"

# With ttl=0 every per-channel sender socket of the package joins its channel's
# group on interface 0.0.0.0, which the kernel maps to the default-route
# interface (eth0 here): IGMP membership reports would leave the host. Pin those
# joins to loopback so that this peer only ever touches lo. Nothing on the wire
# between peers changes (the sender socket never receives pulicast traffic).
import pulicast.transport.plain_socket_transport as _pst  # noqa: E402

_orig_join = _pst.join_multicast_group


def _loopback_join(sock, group, if_address):
    if if_address in (None, "0.0.0.0"):
        if_address = LOOPBACK
    return _orig_join(sock, group, if_address)


_pst.join_multicast_group = _loopback_join

ZCM_PRIMITIVES = ("int8_msg", "int16_msg", "int32_msg", "int64_msg", "float_msg",
                  "double_msg", "string_msg", "boolean_msg", "byte_msg")


def ready(**info):
    print("READY " + json.dumps(info), file=sys.stderr, flush=True)


def emit(obj):
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


def make_node(args) -> pulicast.ThreadedNode:
    if args.defaults:
        # The package as a user runs it: its own interface choice and joins.
        _pst.join_multicast_group = _orig_join
        return pulicast.ThreadedNode(args.name, port=args.port,
                                     heartbeat_period=args.heartbeat)
    return pulicast.ThreadedNode(args.name, port=args.port, ttl=0,
                                 heartbeat_period=args.heartbeat,
                                 interface_address=LOOPBACK)


def to_jsonable(v):
    """Decoded value -> JSON: bytes as hex, ZCM structs as dicts."""
    if isinstance(v, (bytes, bytearray)):
        return bytes(v).hex()
    if isinstance(v, float) and (v != v or v in (float("inf"), float("-inf"))):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return [to_jsonable(x) for x in v]
    if hasattr(v, "__slots__") and hasattr(v, "encode"):
        d = {s: to_jsonable(getattr(v, s)) for s in v.__slots__}
        d["_zcm_type"] = type(v).__name__
        return d
    return v


def source_str(source: Address) -> str:
    return f"{source.ip}:{source.port}"


def parse_value(kind: str, text: str):
    if kind in ("str", "string_msg"):
        return text
    if kind in ("int", "int8_msg", "int16_msg", "int32_msg", "int64_msg", "byte_msg"):
        return int(text, 0)
    if kind in ("float", "float_msg", "double_msg"):
        return float(text)
    if kind in ("bool", "boolean_msg"):
        t = text.strip().lower()
        if t in ("1", "true", "yes", "on"):
            return True
        if t in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"not a bool: {text!r}")
    if kind == "bytes":
        return bytes.fromhex(text)
    if kind == "none":
        return None
    raise ValueError(f"unknown kind {kind}")


# ---------------------------------------------------------------- publish

def cmd_publish(args) -> int:
    node = make_node(args)
    channel = node[args.channel]
    node.start()
    ready(cmd="publish", name=node.name, session_id=node.session_id, channel=channel.name)
    if args.delay > 0:
        time.sleep(args.delay)
    for i in range(args.count):
        text = args.value.format(i=i) if "{" in args.value else args.value
        value = parse_value(args.kind, text)
        if args.kind in ZCM_PRIMITIVES:
            msg = getattr(pulicast_messages, args.kind)()
            msg.value = value
            channel << msg
        else:
            channel << value
        if args.period > 0 and i + 1 < args.count:
            time.sleep(args.period)
    emit({"published": args.count, "channel": channel.name, "name": node.name,
          "session_id": node.session_id})
    if args.linger > 0:
        time.sleep(args.linger)
    node.stop()
    return 0


# -------------------------------------------------------------- subscribe

_TYPED = {"str": str, "int": int, "float": float, "bool": bool, "bytes": bytes}


def cmd_subscribe(args) -> int:
    node = make_node(args)
    channel = node[args.channel]
    got: "queue.Queue[dict]" = queue.Queue()
    universal = get_message_decoder(Any)

    def record(value, lead, source, raw=None, type_name=None):
        rec = {"channel": channel.name, "value": to_jsonable(value),
               "type": type_name or type(value).__name__, "lead": lead,
               "source": source_str(source)}
        if raw is not None:
            rec["raw"] = bytes(raw).hex()
        got.put(rec)

    if args.as_ == "auto":
        def on_raw(message: bytes, source: Address, lead: int):
            raw = bytes(message)
            try:
                value = universal(bytearray(raw))
            except Exception as e:  # truncated / malformed ZCM payload
                record(raw, lead, source, raw, type_name="decode_error")
                print(f"decode error on {channel.name}: {e!r}", file=sys.stderr, flush=True)
                return
            if value is None:  # unknown fingerprint (or empty): raw bytes
                record(raw, lead, source, raw, type_name="bytes")
            else:
                record(value, lead, source, raw)
        cb = on_raw
    elif args.as_ == "any":
        def on_any(message, source: Address, lead: int):
            record(message, lead, source)
        cb = on_any
    else:
        t = _TYPED[args.as_]

        def on_typed(message, source: Address, lead: int):
            record(message, lead, source)
        on_typed.__annotations__["message"] = t
        cb = on_typed

    if args.ordered:
        channel.subscribe_ordered(cb)
    else:
        channel.subscribe(cb)
    node.start()
    ready(cmd="subscribe", name=node.name, session_id=node.session_id, channel=channel.name)

    deadline = time.monotonic() + args.timeout
    n = 0
    while n < args.count:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        try:
            rec = got.get(timeout=left)
        except queue.Empty:
            break
        emit(rec)
        n += 1
    node.stop()
    if n < args.count:
        print(f"timeout: got {n} of {args.count} messages", file=sys.stderr, flush=True)
        return 1
    return 0


# ------------------------------------------------------------------ nodes

def cmd_nodes(args) -> int:
    node = make_node(args)
    discoverer = NodeDiscoverer(node)
    seen = {}   # session_id -> dict
    lock = threading.Lock()
    t0 = time.monotonic()

    def snapshot(view, alive):
        chans = {}
        for name in view.channels:
            chans[name] = {"name": name, "published": False, "subscribed": False,
                           "period_s": None}
        for pub in view.publications.values():
            c = chans.setdefault(pub.name, {"name": pub.name, "subscribed": False})
            c["published"] = True
            c["period_s"] = pub.period
        for name in view.subscriptions:
            c = chans.setdefault(name, {"name": name, "published": False, "period_s": None})
            c["subscribed"] = True
        return {"name": view.name, "session_id": view.session_id,
                "source": source_str(view.source),
                "heartbeat_period_s": view.heartbeat_period,
                "channels": sorted(chans.values(), key=lambda c: c["name"]),
                "alive": alive}

    def on_added(view):
        with lock:
            rec = snapshot(view, True)
            rec["first_seen_s"] = round(time.monotonic() - t0, 3)
            seen[view.session_id] = rec

    def on_removed(view):
        with lock:
            rec = snapshot(view, False)
            rec["first_seen_s"] = seen.get(view.session_id, {}).get("first_seen_s")
            rec["died_s"] = round(time.monotonic() - t0, 3)
            seen[view.session_id] = rec

    discoverer.add_on_item_added_callback(on_added)
    discoverer.add_on_item_removed_callback(on_removed)
    node.start()
    ready(cmd="nodes", name=node.name, session_id=node.session_id)
    time.sleep(args.for_)
    with lock:
        for view in list(discoverer.values()):  # refresh channels of live nodes
            first = seen.get(view.session_id, {}).get("first_seen_s")
            rec = snapshot(view, True)
            rec["first_seen_s"] = first
            seen[view.session_id] = rec
        out = sorted(seen.values(), key=lambda r: (r["name"], r["session_id"]))
    if not args.include_self:
        out = [r for r in out if r["session_id"] != node.session_id]
    node.stop()
    print(json.dumps(out, indent=None))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)

    def common(sp):
        sp.add_argument("--port", type=int, default=pulicast.DEFAULT_PORT)
        sp.add_argument("--name", required=True, help="node name")
        sp.add_argument("--heartbeat", type=float, default=0.1,
                        help="heartbeat period in seconds (default 0.1)")
        sp.add_argument("--defaults", action="store_true",
                        help="the package's own interface defaults instead of loopback "
                             "(its joins then go to the default route's interface: only "
                             "inside a test's own network namespace)")

    sp = sub.add_parser("publish")
    common(sp)
    sp.add_argument("--channel", required=True)
    sp.add_argument("--kind", required=True,
                    choices=["str", "int", "float", "bool", "bytes", "none", *ZCM_PRIMITIVES])
    sp.add_argument("--value", default="")
    sp.add_argument("--count", type=int, default=1)
    sp.add_argument("--period", type=float, default=0.05, help="seconds between messages")
    sp.add_argument("--delay", type=float, default=0.0, help="seconds to wait before the first")
    sp.add_argument("--linger", type=float, default=0.0, help="seconds to stay alive afterwards")
    sp.set_defaults(func=cmd_publish)

    sp = sub.add_parser("subscribe")
    common(sp)
    sp.add_argument("--channel", required=True)
    sp.add_argument("--count", type=int, default=1)
    sp.add_argument("--timeout", type=float, default=10.0)
    sp.add_argument("--as", dest="as_", default="auto",
                    choices=["auto", "any", "bytes", "str", "int", "float", "bool"])
    sp.add_argument("--ordered", action="store_true", help="subscribe_ordered (drop lead < 1)")
    sp.set_defaults(func=cmd_subscribe)

    sp = sub.add_parser("nodes")
    common(sp)
    sp.add_argument("--for", dest="for_", type=float, default=1.0)
    sp.add_argument("--include-self", action="store_true")
    sp.set_defaults(func=cmd_nodes)

    args = p.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())

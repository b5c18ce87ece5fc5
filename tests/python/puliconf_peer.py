#!/usr/bin/env python3
"""Pulicast 2.x distributed settings, driven through the reference package
(pulicast==2.0.1, `pulicast_tools.puliconf`) on a trio node. Its `cli.py`
needs Qt, so this calls the same functions the CLI calls. Traffic stays on
loopback: interface 127.0.0.1, TTL 0.

    puliconf_peer.py own  --port P --name NODE --ns NS --for S SPEC...
        SPEC is NAME=TYPE:VALUE[:LO,HI] (TYPE: float, int, str, bool). A
        range gives the setting the 2.x validator `accept_range(LO, HI)`.
        Prints "READY {}" on stderr once the settings exist, then one JSON line
        per change {"name", "value"} on stdout; at the end one JSON object
        of every setting's value.
    puliconf_peer.py pull --port P                  TOML of every setting on stdout
    puliconf_peer.py push --port P FILE [--reset-first] [--unset-first]
        JSON {"changed", "unchanged", "failed"} (setting names) on stdout
    puliconf_peer.py diff --port P FILE             TOML diff on stdout
    puliconf_peer.py set  --port P NAME VALUE       JSON {"ok", "message", "value"}

pull, push, diff and set wait as puliconf does: until no new setting has
appeared for 2 s.
"""
import argparse
import json
import logging
import sys
import types

# The package's __init__ imports its Qt node (PySide2, not installable here).
_qt = types.ModuleType("pulicast.pulicast_qt")
_qt.QtNode = object
sys.modules.setdefault("pulicast.pulicast_qt", _qt)

import tomlkit  # noqa: E402
import trio  # noqa: E402
from pulicast.discovery.node_discoverer import NodeDiscoverer  # noqa: E402
from pulicast.pulicast_trio import TrioNode  # noqa: E402
from pulicast.transport import trio_multicast_transport  # noqa: E402
from pulicast_tools.puliconf.setting import Setting, accept_range  # noqa: E402
from pulicast_tools.puliconf.setting_discoverer import SettingDiscoverer  # noqa: E402
from pulicast_tools.puliconf.utils import (  # noqa: E402
    convert_toml_value_to_puli_serializable, diff_configuration, pull_configuration,
    push_configuration, wait_until_no_new_setting_appeared)



async def _send(self, packet, group):
    # The package sends through a private trio helper whose signature
    # changed after trio 0.21; this is the public call its own comment
    # names as the equivalent (only slower).
    await self._socket.sendto(packet, (group, self._port))


trio_multicast_transport.TrioChannelSender.async_send = _send

TYPES = {"float": float, "int": int, "str": str, "bool": lambda s: s.lower() == "true"}


def node(nursery, args, name="puliconf"):
    return TrioNode(name, nursery, port=args.port, ttl=0, interface_address="127.0.0.1")


async def own(args):
    async with trio.open_nursery() as nursery:
        n = TrioNode(args.name, nursery, port=args.port, ttl=0, interface_address="127.0.0.1",
                     default_namespace="/" + args.ns if args.ns else "/")
        settings = {}
        for spec in args.specs:
            name, rest = spec.split("=", 1)
            parts = rest.split(":")
            kind, value = parts[0], TYPES[parts[0]](parts[1])
            kwargs = {}
            if len(parts) > 2:
                lo, hi = (TYPES[kind](x) for x in parts[2].split(","))
                kwargs["validate_roc"] = accept_range(lo, hi)

            def changed(name=name):
                print(json.dumps({"name": name, "value": settings[name].value}), flush=True)
            settings[name] = Setting(name, n, initial_value=value, value_changed=changed, **kwargs)
        print("READY {}", file=sys.stderr, flush=True)
        await trio.sleep(args.for_)
        print(json.dumps({k: s.value for k, s in settings.items()}), flush=True)
        nursery.cancel_scope.cancel()


async def with_settings(args, work):
    async with trio.open_nursery() as nursery:
        n = node(nursery, args)
        discoverer = NodeDiscoverer(n)
        settings = SettingDiscoverer(n, nursery, discoverer).settings_set
        await work(settings)
        nursery.cancel_scope.cancel()


async def pull(args):
    async def work(settings):
        doc = await pull_configuration(settings)
        sys.stdout.write(tomlkit.dumps(doc))
    await with_settings(args, work)


async def push(args):
    doc = tomlkit.parse(open(args.file).read())

    async def work(settings):
        changed, unchanged, failed = await push_configuration(settings, doc, args.reset_first, args.unset_first)
        print(json.dumps({k: sorted(s.name for s in v) for k, v in
                          [("changed", changed), ("unchanged", unchanged), ("failed", failed)]}))
    await with_settings(args, work)


async def diff(args):
    doc = tomlkit.parse(open(args.file).read())

    async def work(settings):
        sys.stdout.write(tomlkit.dumps(await diff_configuration(settings, doc)))
    await with_settings(args, work)


async def set_(args):
    async def work(settings):
        await wait_until_no_new_setting_appeared(settings)
        found = [s for s in settings if s.name == args.name]
        if not found:
            print(json.dumps({"ok": False, "message": "unknown setting", "value": None}))
            return
        s = found[0]
        target = convert_toml_value_to_puli_serializable(tomlkit.parse(f"v = {args.value}")["v"], s.value_type)
        ok, message = await s.set(target)
        print(json.dumps({"ok": ok, "message": message, "value": s.value}))
    await with_settings(args, work)


def main():
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd", required=True)
    o = sub.add_parser("own")
    o.add_argument("--name", default="py_owner")
    o.add_argument("--ns", default="")
    o.add_argument("--for", dest="for_", type=float, default=10)
    o.add_argument("specs", nargs="+")
    sub.add_parser("pull")
    for name in ("push", "diff"):
        c = sub.add_parser(name)
        c.add_argument("file")
    sub.choices["push"].add_argument("--reset-first", action="store_true")
    sub.choices["push"].add_argument("--unset-first", action="store_true")
    s = sub.add_parser("set")
    s.add_argument("name")
    s.add_argument("value")
    for c in sub.choices.values():
        c.add_argument("--port", type=int, required=True)
    args = p.parse_args()
    trio.run({"own": own, "pull": pull, "push": push, "diff": diff, "set": set_}[args.cmd], args)


if __name__ == "__main__":
    main()

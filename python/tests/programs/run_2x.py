"""Runs a 2.x program on the reference package (pulicast==2.0.1), made
safe for this machine as tests/python/peer.py does: the package's Qt node
stubbed (PySide2 is not installable here) and its sockets' multicast joins
pinned to loopback. The program itself is run unchanged.

    run_2x.py PROGRAM ARGS...
"""

import runpy
import sys
import types

_qt = types.ModuleType("pulicast.pulicast_qt")
_qt.QtNode = object
sys.modules.setdefault("pulicast.pulicast_qt", _qt)

import pulicast.transport.plain_socket_transport as _pst  # noqa: E402

_join = _pst.join_multicast_group


def _loopback_join(sock, group, if_address):
    return _join(sock, group, "127.0.0.1" if if_address in (None, "0.0.0.0") else if_address)


_pst.join_multicast_group = _loopback_join

program = sys.argv[1]
sys.argv = sys.argv[1:]
runpy.run_path(program, run_name="__main__")

#!/usr/bin/env python3
"""Tiny UDP probe for the netns test hosts (plain socket module, no deps).

  mcast.py recv  --iface IP [--group G] --port P [--idle S] [--max-secs S] [--ready FILE]
  mcast.py send  --iface IP [--group G] --port P [--count N] [--gap S] [--ttl T]
  mcast.py urecv --iface IP --port P [--idle S] [--max-secs S] [--ready FILE]
  mcast.py usend --iface IP --dest IP --port P [--count N] [--gap S]

recv joins G on the interface with address IP and counts datagrams until no
datagram came for --idle seconds (after the first one) or --max-secs passed;
--ready FILE is created once the socket is joined. send sends --count numbered
datagrams (TTL --ttl, default 1) out of IP. Both print one JSON line. Every loop
is bounded in count and time.
"""
import argparse
import json
import socket
import struct
import sys
import time


def recv_loop(sock, args):
    if args.ready:
        open(args.ready, "w").close()
    seqs = set()
    total = 0
    senders = set()
    start = time.monotonic()
    last = None
    while True:
        now = time.monotonic()
        if now - start >= args.max_secs:
            break
        if last is not None and now - last >= args.idle:
            break
        wait = args.max_secs - (now - start)
        if last is not None:
            wait = min(wait, args.idle - (now - last))
        sock.settimeout(max(wait, 0.001))
        try:
            data, addr = sock.recvfrom(65535)
        except socket.timeout:
            continue
        last = time.monotonic()
        total += 1
        senders.add(addr[0])
        if data.startswith(b"seq "):
            seqs.add(int(data.split()[1]))
    print(json.dumps({"received": total, "unique": len(seqs), "senders": sorted(senders)}))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("mode", choices=["recv", "send", "urecv", "usend"])
    p.add_argument("--iface", required=True)
    p.add_argument("--group", default="239.1.2.3")
    p.add_argument("--dest")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--count", type=int, default=10)
    p.add_argument("--gap", type=float, default=0.0002)
    p.add_argument("--ttl", type=int, default=1)
    p.add_argument("--idle", type=float, default=1.0)
    p.add_argument("--max-secs", type=float, default=10.0)
    p.add_argument("--ready")
    args = p.parse_args()
    if args.count > 100000 or args.max_secs > 120:
        sys.exit("limits: --count <= 100000, --max-secs <= 120")

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if args.mode == "recv":
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        s.bind((args.group, args.port))
        mreq = struct.pack("4s4s", socket.inet_aton(args.group), socket.inet_aton(args.iface))
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
        recv_loop(s, args)
    elif args.mode == "urecv":
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        s.bind((args.iface, args.port))
        recv_loop(s, args)
    else:
        if args.mode == "send":
            dest = args.group
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, args.ttl)
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(args.iface))
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 0)
        else:
            dest = args.dest
        s.bind((args.iface, 0))
        sent = errors = 0
        err_names = set()
        deadline = time.monotonic() + 60
        for i in range(args.count):
            if time.monotonic() > deadline:
                break
            try:
                s.sendto(b"seq %d" % i, (dest, args.port))
                sent += 1
            except OSError as e:
                errors += 1
                err_names.add(e.strerror)
            if args.gap:
                time.sleep(args.gap)
        print(json.dumps({"sent": sent, "errors": errors, "error_kinds": sorted(err_names)}))


if __name__ == "__main__":
    main()

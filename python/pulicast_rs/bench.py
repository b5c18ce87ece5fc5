"""`python -m pulicast_rs.bench thr|lat`: pulicast_rs against a raw
Python UDP socket, the Pulicast 2.x reference package and the Rust API, in
one run, with default settings (docs/python.md, "Speed").

    python -m pulicast_rs.bench thr [--size 64] [--for 1.0] [--runs 3]
    python -m pulicast_rs.bench lat [--size 64] [--rounds 2000] [--runs 2]
        [--reference-python PATH]   the 2.x package's interpreter (its rows are left out without it)
        [--puli PATH]               the `puli` binary, for the Rust rows (left out without it)
        [--receive-spin SECONDS]    every pulicast_rs node spins so long (a tuned run: the header says so)
        [--pin]                     lat: the Python pinger on CPU 0, the ponger on CPU 1 (tuned, said too)

`thr`: a publisher process sends as fast as it can for `--for` seconds;
the subscriber (this process, or the 2.x package's own) counts what
arrives: msg/s from its first message to its last, and the loss against
what was sent. Rows are interleaved, the median of `--runs` reported.
`lat`: this process publishes a ping and waits for a pong process's
answer, `--rounds` times per run; percentiles of all runs. Traffic stays
on loopback (multicast on 127.0.0.1, TTL 0); every loop ends by count or
time.
"""

import argparse
import json
import os
import socket
import statistics
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

GROUP = "239.255.76.67"
HERE = Path(__file__).resolve().parent


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def raw_socket(port: int, receive: bool) -> socket.socket:
    """A multicast socket on loopback, as pulicast's: TTL 0, 127.0.0.1."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    if receive:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        s.bind(("", port))
        membership = struct.pack("4s4s", socket.inet_aton(GROUP), socket.inet_aton("127.0.0.1"))
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
    return s


# A receive spin for every pulicast_rs node of the run (`--receive-spin`,
# handed to the role processes): a tuned setting, said in the header.
SPIN_ENV = "PULICAST_RS_BENCH_SPIN"


def node(port: int, name: str):
    import pulicast_rs

    spin = os.environ.get(SPIN_ENV)
    extra = {"receive_spin": float(spin)} if spin else {}
    return pulicast_rs.Node(name, port=port, interface="127.0.0.1", keys_from_env=False, **extra)


def tuned(args) -> str:
    """What the header says of a tuned run."""
    said = []
    if args.receive_spin is not None:
        said.append(f"pulicast_rs receive_spin {args.receive_spin * 1e6:.0f} µs")
    if getattr(args, "pin", False):
        said.append("Python pinger on CPU 0 and ponger on CPU 1")
    return "default settings" + (" except " + ", ".join(said) if said else "")


# --- the roles other processes play -------------------------------------


def role_pub(kind: str, port: int, size: int, secs: float) -> None:
    payload = bytes(size)
    time.sleep(0.5)  # the subscriber joins
    sent, end = 0, time.monotonic() + secs
    if kind == "raw":
        s = raw_socket(port, receive=False)
        while time.monotonic() < end:
            s.sendto(payload, (GROUP, port))
            sent += 1
    else:
        n = node(port, "bench_pub")
        channel = n.channel("bench/thr")
        while time.monotonic() < end:
            channel.publish(payload)
            sent += 1
        n.stop()
    print(json.dumps({"sent": sent}), flush=True)


def role_pong(kind: str, port: int) -> None:
    end = time.monotonic() + 120
    if kind == "raw":
        s = raw_socket(port, receive=True)
        s.settimeout(0.5)
        out = raw_socket(port + 1, receive=False)
        print("READY", flush=True)
        while time.monotonic() < end:
            try:
                data = s.recv(65536)
            except socket.timeout:
                continue
            out.sendto(data, (GROUP, port + 1))
    else:
        n = node(port, "bench_pong")
        pong = n.channel("bench/pong")
        pings = n.channel("bench/ping").subscribe()
        print("READY", flush=True)
        while time.monotonic() < end:
            m = pings.recv(timeout=0.5)
            if m is not None:
                pong.publish_bytes(m.payload)


# --- thr ------------------------------------------------------------------


# `--pin`: the pinger (this process) on CPU 0 and the ponger on CPU 1.
PINNED = False
# The CPUs this process had: the Rust row runs on them, as without `--pin`.
ALL_CPUS = set(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else set()


def on_cpu(cpu: int):
    """What pins a process started to `cpu` under `--pin` (a preexec_fn)."""
    if not PINNED:
        return None
    return lambda: os.sched_setaffinity(0, {cpu})


def spawn(args, **kw):
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, **kw)


def publisher(kind, port, size, secs, puli=None, batch_us=None):
    if kind == "rust":
        # `puli bench`'s own publisher role, on channel bench/thr0.
        args = [puli, "bench", "thr-pub", "--path", "await", "--port", str(port), "--size", str(size), "--for", str(secs)]
        if batch_us:
            args += ["--batch-us", str(batch_us)]
        return spawn(args)
    return spawn([sys.executable, "-m", "pulicast_rs.bench", "_pub", kind, str(port), str(size), str(secs)])


def sent_by(p) -> int:
    out, _ = p.communicate(timeout=60)
    return json.loads(out.strip().splitlines()[-1])["sent"]


def thr_python(row: str, size: int, secs: float, puli=None) -> dict:
    """One run of a Python subscriber row; its publisher is Python, or
    Rust (`puli`) for the rows that say so."""
    port = free_port()
    kind, channel_name, batch_us = "rs", "bench/thr", None
    if "Rust publisher" in row:
        kind, channel_name = "rust", "bench/thr0"
        batch_us = 1000 if "batched" in row else None
    got = {"n": 0, "first": None, "last": None}

    def count(now):
        if got["first"] is None:
            got["first"] = now
        got["last"] = now
        got["n"] += 1

    if row == "raw socket":
        s = raw_socket(port, receive=True)
        s.settimeout(0.3)
        p = publisher("raw", port, size, secs)
        while True:
            try:
                s.recv(65536)
            except socket.timeout:
                if p.poll() is not None:
                    break
                continue
            count(time.monotonic())
        s.close()
    else:
        n = node(port, "bench_sub")
        channel = n.channel(channel_name)
        if row.startswith("pulicast_rs callback"):
            # Each row reads every message's value, as the 2.x row's
            # callback is handed its bytes: decoding is part of the cost.
            keep = channel.subscribe(lambda m: (m.value, count(time.monotonic())))
            p = publisher(kind, port, size, secs, puli, batch_us)
            last = -1
            while p.poll() is None or got["n"] != last:
                last = got["n"]
                time.sleep(0.3)
            keep.close()
        else:
            sub = channel.subscribe()
            p = publisher(kind, port, size, secs, puli, batch_us)
            while True:
                if row.startswith("pulicast_rs recv_many"):
                    batch = sub.recv_many(4096, timeout=0.3)
                    if not batch:
                        if p.poll() is not None:
                            break
                        continue
                    now = time.monotonic()
                    for m in batch:
                        m.value
                        count(now)
                else:
                    m = sub.recv(timeout=0.3)
                    if m is None:
                        if p.poll() is not None:
                            break
                        continue
                    m.value
                    count(time.monotonic())
        n.stop()
    sent = sent_by(p)
    return rate(got["n"], got["first"], got["last"], sent)


def thr_2x(python: str, size: int, secs: float) -> dict:
    port = free_port()
    recv = spawn([python, str(HERE / "_bench2x.py"), "recv", str(port), str(secs + 3)])
    assert recv.stdout.readline().startswith("READY")
    pub = spawn([python, str(HERE / "_bench2x.py"), "pub", str(port), str(size), str(secs)])
    sent = sent_by(pub)
    out, _ = recv.communicate(timeout=60)
    got = json.loads(out.strip().splitlines()[-1])
    return rate(got["received"], got["first"], got["last"], sent)


def thr_rust(puli: str, size: int, secs: float) -> dict:
    """`puli bench thr`'s `await` row (a Rust publisher and a Rust
    subscriber awaiting `recv()`), one run."""
    out = subprocess.run(
        [puli, "bench", "thr", "--size", str(size), "--rows", "await", "--rounds", "1", "--for", str(secs), "--json"],
        capture_output=True, text=True, timeout=300,
    )
    row = json.loads(out.stdout)["results"][0]["rows"]["await"]
    return {"msg_s": row["msgs_per_s"], "loss": row["loss"]}


def rate(n, first, last, sent) -> dict:
    msg_s = (n - 1) / (last - first) if n > 1 and last > first else 0.0
    return {"msg_s": msg_s, "loss": 1 - n / sent if sent else 0.0}


def thr(args) -> None:
    rows = ["raw socket", "pulicast_rs iterator", "pulicast_rs callback", "pulicast_rs recv_many"]
    if args.reference_python:
        rows.append("2.x package")
    if args.puli:
        rows.append("Rust, recv().await")
        # What a Python subscriber takes from a faster (Rust) publisher;
        # the last row batches (1 ms), a tuned setting.
        rows += [
            "pulicast_rs iterator, Rust publisher",
            "pulicast_rs callback, Rust publisher",
            "pulicast_rs recv_many, Rust publisher",
            "pulicast_rs recv_many, Rust publisher batched 1 ms",
        ]
    results = {row: [] for row in rows}
    for _ in range(args.runs):
        for row in rows:
            if row == "2.x package":
                results[row].append(thr_2x(args.reference_python, args.size, args.secs))
            elif row.startswith("Rust"):
                results[row].append(thr_rust(args.puli, args.size, args.secs))
            else:
                results[row].append(thr_python(row, args.size, args.secs, args.puli))
    print(f"throughput, {args.size} B, publisher and subscriber in separate processes, loopback multicast, "
          f"{tuned(args)}, unbatched but for the row that says so, median of {args.runs} runs of {args.secs} s")
    print("| row | msg/s | loss | vs raw socket | vs 2.x |")
    print("|---|---:|---:|---:|---:|")
    median = {row: statistics.median(r["msg_s"] or 0 for r in results[row]) for row in rows}
    for row in rows:
        loss = statistics.median(r["loss"] or 0 for r in results[row])
        vs_raw = median[row] / median["raw socket"] if median["raw socket"] else 0
        vs_2x = f"{median[row] / median['2.x package']:.2f}" if median.get("2.x package") else "-"
        print(f"| {row} | {median[row]:,.0f} | {100 * loss:.1f} % | {vs_raw:.2f} | {vs_2x} |")


# --- lat ------------------------------------------------------------------


def lat_python(kind: str, size: int, rounds: int) -> list:
    port = free_port()
    pong = spawn([sys.executable, "-m", "pulicast_rs.bench", "_pong", kind, str(port)], preexec_fn=on_cpu(1))
    try:
        assert pong.stdout.readline().startswith("READY")
        payload = bytes(size)
        rtts = []
        if kind == "raw":
            out = raw_socket(port, receive=False)
            back = raw_socket(port + 1, receive=True)
            back.settimeout(1.0)
            time.sleep(0.3)
            back.settimeout(0.2)
            for _ in range(rounds):
                start = time.perf_counter()
                out.sendto(payload, (GROUP, port))
                try:
                    back.recv(65536)
                except socket.timeout:
                    continue
                rtts.append((time.perf_counter() - start) * 1e6)
        else:
            n = node(port, "bench_ping")
            ping = n.channel("bench/ping")
            pongs = n.channel("bench/pong").subscribe()
            time.sleep(0.5)
            for _ in range(rounds):
                start = time.perf_counter()
                ping.publish_bytes(payload)
                if pongs.recv(timeout=0.2) is not None:
                    rtts.append((time.perf_counter() - start) * 1e6)
            n.stop()
        return rtts
    finally:
        pong.kill()
        pong.wait()


def lat_2x(python: str, size: int, rounds: int) -> list:
    port = free_port()
    pong = spawn([python, str(HERE / "_bench2x.py"), "pong", str(port)], preexec_fn=on_cpu(1))
    try:
        assert pong.stdout.readline().startswith("READY")
        out = subprocess.run([python, str(HERE / "_bench2x.py"), "ping", str(port), str(size), str(rounds)],
                             capture_output=True, text=True, timeout=300, preexec_fn=on_cpu(0))
        return json.loads(out.stdout.strip().splitlines()[-1])["rtt_us"]
    finally:
        pong.kill()
        pong.wait()


def lat_rust(puli: str, size: int, rounds: int) -> dict:
    """`puli bench lat`'s `await` row, one run."""
    out = subprocess.run(
        [puli, "bench", "lat", "--size", str(size), "--rows", "await", "--rounds", str(rounds), "--runs", "1", "--json"],
        capture_output=True, text=True, timeout=300,
        preexec_fn=(lambda: os.sched_setaffinity(0, ALL_CPUS)) if PINNED else None,
    )
    return json.loads(out.stdout)["rows_us"]["await"]


def lat(args) -> None:
    rows = {"raw socket": [], "pulicast_rs iterator": []}
    if args.reference_python:
        rows["2.x package"] = []
    for _ in range(args.runs):
        rows["raw socket"] += lat_python("raw", args.size, args.rounds)
        rows["pulicast_rs iterator"] += lat_python("rs", args.size, args.rounds)
        if args.reference_python:
            rows["2.x package"] += lat_2x(args.reference_python, args.size, args.rounds)
    print(f"round trip, {args.size} B, Python pinger and ponger processes, loopback multicast, "
          f"{tuned(args)}, {args.runs} runs of {args.rounds}")
    print("| row | p50 µs | p99 µs | answered |")
    print("|---|---:|---:|---:|")
    for row, rtts in rows.items():
        q = statistics.quantiles(rtts, n=100) if len(rtts) > 1 else [0] * 99
        print(f"| {row} | {q[49]:.0f} | {q[98]:.0f} | {len(rtts)} of {args.runs * args.rounds} |")
    if args.puli:
        rust = lat_rust(args.puli, args.size, args.rounds)
        print(f"| Rust, recv().await (puli bench lat) | {rust['p50']:.0f} | {rust['p99']:.0f} | |")


def main(argv=None) -> None:
    if argv is None:
        argv = sys.argv[1:]
    if argv and argv[0] == "_pub":
        return role_pub(argv[1], int(argv[2]), int(argv[3]), float(argv[4]))
    if argv and argv[0] == "_pong":
        return role_pong(argv[1], int(argv[2]))
    p = argparse.ArgumentParser(prog="python -m pulicast_rs.bench", description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["thr", "lat"])
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--for", dest="secs", type=float, default=1.0)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--rounds", type=int, default=2000)
    p.add_argument("--reference-python", default=os.environ.get("PULICAST_2X_PYTHON"))
    p.add_argument("--puli", default=None)
    p.add_argument("--pin", action="store_true",
                   help="lat: the Python pinger on CPU 0 and the ponger on CPU 1 (a tuned run)")
    p.add_argument("--receive-spin", type=float, default=None,
                   help="seconds every pulicast_rs node's receive loop spins (a tuned row; default: the Node's, 0)")
    args = p.parse_args(argv)
    if args.receive_spin is not None:
        os.environ[SPIN_ENV] = str(args.receive_spin)
    if args.pin:
        if len(os.sched_getaffinity(0)) < 2:
            p.error("--pin needs two CPUs")
        global PINNED
        PINNED = True
        os.sched_setaffinity(0, {0})
    (thr if args.what == "thr" else lat)(args)


if __name__ == "__main__":
    main()

"""The benchmark runs (a smoke run: rows and numbers present, no timing
asserted; the figures are in docs/python.md)."""

import os
import subprocess
import sys

from test_compat import reference_python  # noqa: F401 (a fixture)


def run(*args):
    out = subprocess.run([sys.executable, "-m", "pulicast_rs.bench", *args], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_the_benchmark_runs_every_row(reference_python):  # noqa: F811
    table = run("thr", "--runs", "1", "--for", "0.2", "--reference-python", reference_python)
    for row in ("raw socket", "pulicast_rs iterator", "pulicast_rs callback", "pulicast_rs recv_many", "2.x package"):
        line = next(line for line in table.splitlines() if line.startswith(f"| {row} |"))
        assert float(line.split("|")[2].replace(",", "")) > 0, line
    table = run("lat", "--runs", "1", "--rounds", "50", "--reference-python", reference_python)
    for row in ("raw socket", "pulicast_rs iterator", "2.x package"):
        assert any(line.startswith(f"| {row} |") for line in table.splitlines()), table
    # A tuned run says so in its header.
    if len(os.sched_getaffinity(0)) < 2:
        table = run("lat", "--runs", "1", "--rounds", "30", "--receive-spin", "100e-6")
        assert "except pulicast_rs receive_spin 100 µs," in table, table
    else:
        table = run("lat", "--runs", "1", "--rounds", "30", "--receive-spin", "100e-6", "--pin")
        assert "except pulicast_rs receive_spin 100 µs, Python pinger on CPU 0 and ponger on CPU 1" in table, table
    assert "| pulicast_rs iterator |" in table

"""Settings from Python: owned (native and puliconf's 2.x `Setting`), the
fleet's settings client, and the same settings seen and changed by a Rust
node (`puli config`, the demo's rover) and by the 2.x reference puliconf."""

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

import pulicast_rs
import pulicast_rs as pulicast
from conftest import WAIT, eventually
from pulicast_rs.puliconf import (
    Setting,
    accept_everything,
    accept_in_interval,
    accept_nothing,
    accept_range,
)
from test_compat import REPO, reference_python  # noqa: F401 (a fixture)


def test_an_owned_setting_checks_every_change_and_tells_each(make_node):
    owner = make_node("owner", "rover1")
    speed = owner.setting("max_speed", 1.5, range=(0, 2), unit="m/s", description="top speed")
    assert speed.name == "rover1/max_speed"
    assert speed.value == 1.5
    assert speed.about == "top speed; unit: m/s; must be in [0, 2]"
    seen = []
    speed.on_change(seen.append)
    with pytest.raises(ValueError, match=r"must be in \[0, 2\]"):
        speed.value = 3.0
    with pytest.raises(TypeError, match="must be a float"):
        speed.value = "fast"
    assert speed.set(1.0) is True
    assert speed.set(1.0) is False  # unchanged: no news
    speed.value = 2  # an int is a float here, as in Python's arithmetic
    assert seen == [1.0, 2.0]
    assert type(speed.value) is float

    # Each kind of check, and each type.
    assert owner.setting("armed", False, read_only=True).value is False
    mode = owner.ns("arm").setting("mode", "drive", one_of=["drive", "stop"])
    assert mode.name == "rover1/arm/mode"
    with pytest.raises(ValueError, match="must be one of drive, stop"):
        mode.value = "fly"
    wheels = owner.setting("wheels", 4, at_least=2, check=lambda n: None if n % 2 == 0 else "must be even")
    with pytest.raises(ValueError, match="must be even"):
        wheels.value = 5
    with pytest.raises(ValueError, match="at least 2"):
        wheels.value = 0
    wheels.value = 6
    assert wheels.value == 6

    # Bad declarations: each a clear exception, and the node goes on.
    with pytest.raises(TypeError, match="bool, int, float or str, not list"):
        owner.setting("bad", [1])
    with pytest.raises(TypeError, match="range's lowest must be an int"):
        owner.setting("gears", 1, range=(0.5, 2))
    with pytest.raises(ValueError, match="at most 2"):
        owner.setting("too_high", 5, at_most=2)
    with pytest.raises(ValueError):
        owner.setting("bad\x00name", 1.0)
    with pytest.raises(TypeError, match="callable"):
        owner.setting("odd", 1, check=3)
    assert not owner.stopped


def test_the_fleet_settings_client_reads_and_changes_another_nodes_settings(make_node):
    owner = make_node("owner", "rover1")
    speed = owner.setting("max_speed", 1.5, range=(0, 2))
    wheels = owner.setting("wheels", 4, check=lambda n: n % 2 == 0)
    calls = []

    def raising(value):
        calls.append(value)
        raise RuntimeError("a bug in a watcher")

    wheels.on_change(raising)
    fleet = make_node("tool").fleet_settings()
    # Found first (discovery takes a few heartbeats), then listed.
    fleet.get("rover1/wheels", timeout=WAIT)
    listed = {s.name: s for s in fleet.list(quiet=0.3)}
    assert set(listed) >= {"rover1/max_speed", "rover1/wheels"}
    assert listed["rover1/max_speed"].value == 1.5
    assert listed["rover1/max_speed"].owners == ["owner"]
    assert listed["rover1/max_speed"].type_name == "double_msg"
    assert not listed["rover1/max_speed"].locked

    assert fleet.set("rover1/max_speed", 0.7).value == 0.7
    assert speed.value == 0.7
    with pytest.raises(ValueError, match=r"must be in \[0, 2\]"):
        fleet.set("rover1/max_speed", 5)
    with pytest.raises(ValueError, match="refused by the setting's check"):
        fleet.set("rover1/wheels", 3)
    # A watcher that raises changes nothing: the change holds.
    assert fleet.set("rover1/wheels", 6).value == 6
    assert wheels.value == 6
    # Watchers run once the change is confirmed: soon after `set` returns.
    eventually("the watcher", lambda: calls == [6])
    assert fleet.set_text("rover1/max_speed", "1.25").value == 1.25
    assert fleet.get("rover1/max_speed").text == "1.25"
    assert fleet.reset("rover1/max_speed").value == 1.5
    assert speed.value == 1.5
    with pytest.raises(ValueError):
        fleet.unset("rover1/max_speed")  # a range needs a value
    with pytest.raises(pulicast_rs.PulicastError, match="no node owns it"):
        fleet.get("rover9/nothing", timeout=0.3)
    with pytest.raises(TypeError, match="not object"):
        fleet.set("rover1/max_speed", object())
    with pytest.raises(ValueError):
        fleet.get("rover1/max_speed", timeout=-1)


def test_a_check_may_use_the_setting_and_a_watcher_may_change_another(make_node):
    """Python runs on the node's thread inside the setting's bookkeeping:
    reading the setting from its own check, or setting another from a
    watcher, must not deadlock."""
    owner = make_node("owner")
    limit = owner.setting("limit", 10)
    double = owner.setting("double", 0)
    level = owner.setting("level", 1, check=lambda v: None if v <= limit.value else "above the limit")
    # A check may read the setting it checks: it sees the value before.
    made = {}
    step = owner.setting(
        "step", 1, check=lambda v: None if "step" not in made or abs(v - made["step"].value) <= 1 else "one step at a time"
    )
    made["step"] = step
    level.on_change(lambda v: double.set(2 * v))
    fleet = make_node("tool").fleet_settings()
    assert fleet.set("level", 7).value == 7
    eventually("the watcher's change", lambda: double.value == 14)
    with pytest.raises(ValueError, match="above the limit"):
        fleet.set("level", 11)
    assert fleet.set("step", 2).value == 2
    with pytest.raises(ValueError, match="one step at a time"):
        fleet.set("step", 4)
    step.value = 3
    with pytest.raises(ValueError, match="one step at a time"):
        step.value = 1
    # A timeout past what the clock holds is a long wait, not a crash (the
    # owner's own change reaches the client a moment after it is made).
    eventually("the owner's change", lambda: fleet.get("step", timeout=1e19).value == 3)


def test_puliconf_settings_as_2x_declares_them(port):
    node = pulicast.ThreadedNode("rover", port=port, interface_address="127.0.0.1", default_namespace="/rover1")
    tool = pulicast_rs.Node("tool", port=port, interface="127.0.0.1", keys_from_env=False)
    try:
        changed = []
        gain = Setting("gain", node, 0.5, validate_roc=accept_range(0, 1), value_changed=lambda: changed.append(gain.value))
        # 2.x never checks the initial value: only requests, a reset too.
        high = Setting("high", node / "arm", 5.0, validate_roc=accept_range(0, 1))
        serial = Setting("serial", node, "A123", validate_roc=accept_nothing())
        count = Setting("count", node, value_type=int)
        window = Setting("window", node, 6, validate_roc=accept_in_interval(all_above=5, max_v=7))
        assert (gain.name, high.name, count.value, count.get(3)) == ("rover1/gain", "rover1/arm/high", 0, 0)
        assert high.value == 5.0
        fleet = tool.fleet_settings()
        for name in ("rover1/gain", "rover1/serial"):
            fleet.get(name, timeout=WAIT)
        about = {s.name: s.about for s in fleet.list(quiet=0.3)}
        assert about["rover1/gain"].startswith("must be in [0, 1]")
        assert about["rover1/serial"] == "read-only"
        assert fleet.set("rover1/gain", 0.25).value == 0.25
        assert gain.value == 0.25
        eventually("value_changed", lambda: changed == [0.25])
        with pytest.raises(ValueError, match=r"must be in \[0, 1\]"):
            fleet.set("rover1/gain", 2)
        with pytest.raises(ValueError, match=r"must be in \[0, 1\]"):
            fleet.reset("rover1/arm/high")
        with pytest.raises(ValueError, match="read-only"):
            fleet.set("rover1/serial", "B")
        with pytest.raises(ValueError, match=r"must be in \(5, 7\]"):
            fleet.set("rover1/window", 5)
        assert fleet.unset("rover1/count").value is None
        assert count.value is None and count.get(3) == 3
        # 2.x's own refusals of a declaration.
        with pytest.raises(ValueError, match="initial value or a value type"):
            Setting("none", node)
        with pytest.raises(ValueError, match="while its initial value"):
            Setting("mixed", node, 1, value_type=float)
        with pytest.warns(UserWarning, match="redundant"):
            Setting("both", node, 1, value_type=int, validate_roc=accept_everything())
        with pytest.raises(TypeError, match="ZCM classes"):
            Setting("listed", node, [1])
    finally:
        tool.stop()
        node.stop()


def rust_bin(relative: str) -> Path:
    """A binary of the workspace: built by `cargo test --workspace` (CI
    runs it first), else built here."""
    target = Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target"))
    path = target / "debug" / relative
    if not path.exists():
        what = ["--example", relative.split("/")[-1]] if relative.startswith("examples/") else ["--bin", relative]
        subprocess.run(["cargo", "build", "-q", *what], cwd=REPO, check=True, timeout=1800)
    return path


def net(port):
    return ["--port", str(port), "--interface", "127.0.0.1"]


def test_a_rust_node_and_a_python_node_change_each_others_settings(make_node, port):
    owner = make_node("py_owner", "pyrover")
    speed = owner.setting("max_speed", 1.0, range=(0, 2))
    puli = rust_bin("puli")
    out = subprocess.run(
        [str(puli), "config", "set", "pyrover/max_speed", "1.75", *net(port)],
        capture_output=True, text=True, timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert speed.value == 1.75
    refused = subprocess.run(
        [str(puli), "config", "set", "pyrover/max_speed", "9", *net(port)],
        capture_output=True, text=True, timeout=60,
    )
    assert refused.returncode != 0 and "must be in [0, 2]" in refused.stderr + refused.stdout

    rover = subprocess.Popen(
        [str(rust_bin("examples/rover_demo")), "--role", "rover", "--name", "rover1", "--secs", "30", *net(port)],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )
    try:
        fleet = make_node("py_tool").fleet_settings()
        assert fleet.get("rover1/max_speed", timeout=10).value == 0.5
        assert fleet.set("rover1/mode", "stop").value == "stop"
        with pytest.raises(ValueError, match="must be one of drive, stop"):
            fleet.set("rover1/mode", "fly")
    finally:
        rover.kill()
        rover.wait()


def test_the_2x_puliconf_pulls_and_pushes_python_owned_settings(reference_python, make_node, port, tmp_path):  # noqa: F811
    owner = make_node("py_owner", "pyrover")
    speed = owner.setting("max_speed", 1.0, range=(0, 2))
    mode = owner.setting("mode", "drive")
    peer = [reference_python, str(REPO / "tests/python/puliconf_peer.py")]
    pulled = subprocess.run([*peer, "pull", "--port", str(port)], capture_output=True, text=True, timeout=120)
    assert pulled.returncode == 0, pulled.stderr
    lines = pulled.stdout.splitlines()
    assert '"pyrover/max_speed" = 1.0 # must be in [0, 2]' in lines, pulled.stdout
    assert '"pyrover/mode" = "drive"' in lines, pulled.stdout
    wanted = tmp_path / "wanted.toml"
    wanted.write_text('"pyrover/max_speed" = 0.25\n"pyrover/mode" = "stop"\n')
    pushed = subprocess.run([*peer, "push", "--port", str(port), str(wanted)], capture_output=True, text=True, timeout=120)
    assert pushed.returncode == 0, pushed.stderr
    report = json.loads(pushed.stdout)
    assert sorted(report["changed"]) == ["pyrover/max_speed", "pyrover/mode"], report
    assert speed.value == 0.25 and mode.value == "stop"

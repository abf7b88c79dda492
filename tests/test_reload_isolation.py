"""A SIGHUP reload cannot stall the loop or the monitor (D2, D4): the file is
parsed and validated in a child process bounded in time and memory; YAML
alias bombs and oversized files are refused for every config load; error
messages echo a bounded part of a value; the monitor survives whatever a
plugin does at reload and goes on feeding the watchdog."""

from __future__ import annotations

import io
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from mrctl.config import ConfigError, load_experiment
from mrctl.util.schema import MAX_YAML_BYTES, load_yaml

ROOT = Path(__file__).resolve().parents[1]
FIG5 = (ROOT / "config" / "experiments" / "fig5.yaml").read_text()
#: a real clock on a shared machine: the reloads, not the timing, are judged here
OPEN_TIMING = "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n"


def alias_bomb(levels: int = 9) -> str:
    text = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    prev = "a"
    for name in "bcdefghijklmn"[:levels - 1]:
        text += f"{name}: &{name} [{','.join(['*' + prev] * 9)}]\n"
        prev = name
    return text


def test_an_alias_bomb_is_refused_at_once(tmp_path):
    p = tmp_path / "bomb.yaml"
    p.write_text(FIG5 + alias_bomb())
    t0 = time.monotonic()
    with pytest.raises(ConfigError) as e:
        load_experiment(p)
    assert time.monotonic() - t0 < 5.0  # expanded, the bomb is 387 million nodes: minutes
    assert "more than 64 aliases" in str(e.value) and len(str(e.value)) < 500


def test_few_aliases_that_expand_hugely_are_refused(tmp_path):
    p = tmp_path / "wide.yaml"
    p.write_text("a: &a [" + ",".join(["1"] * 2000) + "]\nb: [" + ",".join(["*a"] * 60) + "]\n")
    with pytest.raises(ConfigError) as e:
        load_yaml(p)
    assert "expands to more than 100000 nodes" in str(e.value)
    p.write_text("a: &a [1, *a]\n")
    with pytest.raises(ConfigError) as e:
        load_yaml(p)
    assert "recursive alias" in str(e.value)
    p.write_text("common: &c {x: 1}\nb: *c\nc: [*c, *c]\n")  # a few anchors stay usable
    assert load_yaml(p) == {"common": {"x": 1}, "b": {"x": 1}, "c": [{"x": 1}, {"x": 1}]}


def test_a_file_no_experiment_reaches_is_refused(tmp_path):
    p = tmp_path / "big.yaml"
    p.write_text(FIG5 + "#" * MAX_YAML_BYTES)
    with pytest.raises(ConfigError) as e:
        load_experiment(p)
    assert "too large" in str(e.value) and MAX_YAML_BYTES <= 64 * 1024


def test_error_messages_echo_a_bounded_part_of_a_value(tmp_path):
    p = tmp_path / "huge.yaml"
    p.write_text(FIG5.replace("rate_hz: 1000", "rate_hz: [" + ",".join(["123456789"] * 3000) + "]")
                 .replace("  eps_N_per_A: 3.0", "  eps_N_per_A: '" + "x" * 20000 + "'"))
    t0 = time.monotonic()
    with pytest.raises(ConfigError) as e:
        load_experiment(p)
    msg = str(e.value)
    assert time.monotonic() - t0 < 5.0
    assert "rate_hz: must be a number, got [123456789, 123456789" in msg and len(msg) < 2000, len(msg)


def test_many_errors_are_listed_up_to_a_bound():
    err = ConfigError([f"k{i}: bad " + "y" * 1000 for i in range(10000)])
    assert len(err.errors) == 51 and err.errors[-1] == "… and 9950 more errors"
    assert max(len(e) for e in err.errors) <= 1000


# -- the child process -----------------------------------------------------------
PLUGINS = {
    "hangs_at_import.py": "import time\ntime.sleep(3600)\n",
    "exits_at_import.py": "raise SystemExit(3)\n",
    "eats_memory.py": "x = bytearray(4 << 30)\n",
    "prints_a_lot.py": "import sys\nfor _ in range(100000):\n    print('x' * 100)\n    print('y' * 100, file=sys.stderr)\n"
                       "from mrctl.laws.inverse import SmoothInverse as Law\n",
}


def _plugin_config(tmp_path: Path, module: str) -> Path:
    for name, text in PLUGINS.items():
        (tmp_path / name).write_text(text)
    p = tmp_path / f"{module}.yaml"
    p.write_text(FIG5.replace("law: smooth", f"law: '{module}:Law'"))
    return p


@pytest.fixture
def plugin_dir(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))  # the child gets the daemon's sys.path
    return tmp_path


def test_the_child_returns_the_validated_config():
    from mrctl.daemon.reload import validate_in_child

    node = validate_in_child(ROOT / "config" / "experiments" / "fig5_robust.yaml")
    assert node.to_dict() == load_experiment(ROOT / "config" / "experiments" / "fig5_robust.yaml").to_dict()


@pytest.mark.parametrize("module,expect", [
    ("hangs_at_import", "checking it took longer than 2 s: refused"),
    ("exits_at_import", "SystemExit(3) raised at import"),
    ("eats_memory", "cannot load 'eats_memory:Law': MemoryError"),
])
def test_the_child_is_bounded_in_time_and_memory(plugin_dir, module, expect):
    from mrctl.daemon.reload import validate_in_child

    t0 = time.monotonic()
    with pytest.raises(ConfigError) as e:
        validate_in_child(_plugin_config(plugin_dir, module), timeout_s=2.0, memory_bytes=1 << 30)
    assert expect in str(e.value)
    assert time.monotonic() - t0 < 8.0


def test_what_a_plugin_prints_in_the_child_goes_nowhere(plugin_dir, capfd):
    from mrctl.daemon.reload import validate_in_child

    node = validate_in_child(_plugin_config(plugin_dir, "prints_a_lot"))
    assert node.inverse.law == "prints_a_lot:Law"
    out, err = capfd.readouterr()
    assert "xxxx" not in out and "yyyy" not in err


# -- the daemon ----------------------------------------------------------------
def _run_with_reloads(tmp_path: Path, texts: list[str], duration_s: float = 3.0):
    """The sim-bench daemon in this process; each text in turn is written to
    its config and SIGHUP sent, the next once the previous was answered."""
    from mrctl.daemon.service import RunOptions, Service

    cfg = tmp_path / "exp.yaml"
    cfg.write_text(FIG5 + OPEN_TIMING)
    svc = Service(RunOptions(str(cfg), duration_s=duration_s, live=False, err=io.StringIO(), stream=io.StringIO(),
                             status_socket=str(tmp_path / "st.sock")))
    answered: list[float] = []

    def later():
        while svc.ctl is None or svc.ctl.ticks < 300:
            time.sleep(0.005)
        for text in texts:
            n = svc.reloads_ok + svc.reloads_rejected
            cfg.write_text(text + "\n" + OPEN_TIMING)
            t0 = time.monotonic()
            os.kill(os.getpid(), signal.SIGHUP)
            while svc.reloads_ok + svc.reloads_rejected == n:
                time.sleep(0.005)
            answered.append(time.monotonic() - t0)

    threading.Thread(target=later, daemon=True).start()
    assert svc.run() == 0
    return svc, answered


def test_a_hostile_reload_is_rejected_and_a_good_one_still_applies(tmp_path):
    svc, answered = _run_with_reloads(tmp_path, [FIG5 + alias_bomb(), FIG5 + "#" * (100 * 1024),
                                                 FIG5.replace("c_des: 500.0", "c_des: 700.0")])
    assert (svc.reloads_rejected, svc.reloads_ok) == (2, 1), svc.messages
    assert any("more than 64 aliases" in m for m in svc.messages)
    assert any("too large" in m for m in svc.messages)
    assert len(answered) == 3 and max(answered) < 2.5
    assert all(len(m) < 1000 for m in svc.messages)


# -- the monitor -----------------------------------------------------------------
class _Notes:
    enabled = True
    watchdog_s = 0.1

    def __init__(self) -> None:
        self.sent: list[tuple[float, str]] = []

    def send(self, *lines: str) -> bool:
        self.sent.extend((time.monotonic(), line) for line in lines)
        return True


@pytest.mark.parametrize("plugin", ["exits", "hangs"])
def test_the_monitor_survives_what_a_plugin_does_at_reload(plugin):
    from mrctl.daemon.monitor import Monitor

    notes, ticks, calls, release = _Notes(), [0], [], threading.Event()

    def reload():
        calls.append(time.monotonic())
        if len(calls) == 1:
            if plugin == "exits":
                raise SystemExit(0)
            release.wait(1.0)  # an import that hangs (a bounded one: it is given up after 1 s)

    m = Monitor(notes, lambda: ticks[0], lambda: "line", reload, io.StringIO(), live=False)
    m.start()
    try:
        t0, sighups = time.monotonic(), 0  # each SIGHUP is sent once: the monitor clears the event before it calls
        while time.monotonic() < t0 + 2.5:
            ticks[0] += 1  # a healthy loop
            if sighups == 0 and notes.sent:
                m.reload_event.set()  # the hostile SIGHUP, once the watchdog is being fed
                sighups = 1
            if sighups == 1 and calls and time.monotonic() > calls[0] + 0.3:
                m.reload_event.set()  # a later SIGHUP, while the first reload raises or hangs
                sighups = 2
            time.sleep(0.01)
    finally:
        m.stop()
    pings = [t for t, line in notes.sent if line == "WATCHDOG=1"]
    assert calls and pings[0] < calls[0]
    during = [t for t in pings if calls[0] < t < calls[0] + 0.9]  # while the first reload raises or hangs
    assert len(during) >= 5, (len(during), len(pings))  # every 50 ms: ~18
    assert max(b - a for a, b in zip(pings, pings[1:])) < 0.7  # the hang lasts 1 s
    assert len(calls) == 2  # the later reload ran

"""Loopback HIL helpers for the tests: see :mod:`hil_sim.testing.harness`.

The protocol tests run the shipped experiments and benches at
:data:`HIL_TEST_RATE_HZ`, a rate this machine holds in CI with both
processes on its 2 cores, and **fail** on a refused start, a lost link or a
protocol error: they never skip for load. 1 kHz over these links is a
timing figure, measured by ``bench/hil_loop.py`` (docs/performance.md), not
a test.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from hil_sim.testing.harness import ROOT, HilSim, hil_tracking, run_daemon  # noqa: F401
from mrctl.config import load_yaml
from mrctl.daemon.recorder import read_sidecar

#: the rate of the protocol tests (daemon and bench): 5 ms a tick leaves the
#: link, both processes and a loaded CI box room
HIL_TEST_RATE_HZ = 200.0
#: reply timeout of the tests' links: most of a 5 ms tick (a reply that comes
#: later is a link error, and a test about the protocol must not count the
#: machine's scheduling as one)
HIL_TEST_TIMEOUT_S = 0.004
#: the tests judge the protocol (the device follows, 0 A at the end, the log
#: complete, the loop closed), not this machine's timing: the run's own
#: acceptance is tested in test_acceptance.py and test_hil_verdict.py
PROTOCOL_ACCEPTANCE = {"max_skipped_share": 1.0, "max_gap_s": 3600.0, "max_fault_share": 0.2,
                       "max_zero_stretch_s": 2.0}
RUN_S = 4.0


def _absolute_files(node: Any, base: Path) -> Any:
    """The YAML tree with every relative path that names a file beside the
    original made absolute (the copy lives elsewhere)."""
    if isinstance(node, dict):
        return {k: _absolute_files(v, base) for k, v in node.items()}
    if isinstance(node, list):
        return [_absolute_files(v, base) for v in node]
    if isinstance(node, str) and "/" in node and not node.startswith("/") and (base / node).is_file():
        return str((base / node).resolve())
    return node


def bench_at_test_rate(bench: Path | str, d: Path, rate_hz: float = HIL_TEST_RATE_HZ) -> str:
    """A copy of a hil_sim bench YAML at ``rate_hz`` (written as JSON, valid YAML)."""
    data = _absolute_files(load_yaml(Path(bench)), Path(bench).parent)
    data["rate_hz"] = rate_hz
    p = d / f"bench-{Path(bench).stem}.yaml"
    p.write_text(json.dumps(data, indent=1) + "\n")
    return str(p)


def experiment_at_test_rate(path: Path, d: Path, rate_hz: float = HIL_TEST_RATE_HZ,
                            acceptance: dict[str, Any] | None = None, **replace: str) -> Path:
    """A shipped HIL experiment, its text first edited by ``replace``
    (old=new), then at ``rate_hz`` with the tests' reply timeout and
    acceptance bounds."""
    text = Path(path).read_text()
    for old, new in replace.items():
        assert old in text, f"{path.name} has no {old!r}"
        text = text.replace(old, new)
    tmp = d / f"src-{Path(path).name}"
    tmp.write_text(text)
    data = _absolute_files(load_yaml(tmp), Path(path).parent)
    data["rate_hz"] = rate_hz
    data["backend"] = {**data["backend"], "timeout_s": HIL_TEST_TIMEOUT_S}
    data["acceptance"] = dict(PROTOCOL_ACCEPTANCE if acceptance is None else acceptance)
    p = d / Path(path).name
    p.write_text(json.dumps(data, indent=1) + "\n")
    return p


def run_hil(tmp_path, start, make_cfg, duration_s: float = RUN_S):
    """Run the daemon against a fresh hil_sim, once. A refused start, a lost
    link or a protocol error fails the test, with the daemon's stderr."""
    d = tmp_path / "run"
    d.mkdir()
    hil = start(d)
    try:
        cfg = make_cfg(d, hil)
        res = run_daemon(cfg, d / "run.csv", duration_s=duration_s)
    finally:
        code = hil.stop()
    # 0, or 5: completed, its verdict degraded by this machine's load (the
    # verdict itself is tested in test_hil_verdict.py); anything else failed
    if res.returncode not in (0, 5):
        pytest.fail(f"HIL run failed: exit {res.returncode}: {res.stderr.strip()[-2000:]}")
    return d, cfg, res, code


def protocol_errors(side: dict[str, Any]) -> tuple[int, int]:
    """(frame and device errors, exchanges) of a run: what a protocol
    regression raises; timeouts are the machine's, not counted."""
    link = side["summary"].get("link") or {}
    return link.get("frame_errors", 0) + link.get("device_errors", 0), link.get("exchanges", 0)


def expected_rows(side: dict[str, Any], settle_s: float = 1.0, duration_s: float = RUN_S) -> float:
    """Ticks after the settle window at the rate the run really ran."""
    return (duration_s - settle_s) * float(side["rate_hz"])


__all__ = ["ROOT", "HilSim", "hil_tracking", "run_daemon", "read_sidecar", "run_hil", "bench_at_test_rate",
           "experiment_at_test_rate", "expected_rows", "HIL_TEST_RATE_HZ"]

"""One run-log format: ``mrctl run`` and ``mrctl simulate`` write the same plain
CSV, column for column, and a sidecar that says what every column means."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from mrctl.cli import main
from mrctl.daemon.service import RunOptions, Service

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"
#: the columns that mean the same thing on a simulated bench whatever ran it
SAME = ("t", "x", "v", "F_des", "F", "I", "k", "seq", "t_dev", "I_applied", "F_true", "fault", "link_errors")


class VirtualClock:
    """No tick is ever late: the daemon's run is deterministic (tests/test_service.py)."""

    def __init__(self):
        self.t = 0

    def now(self):
        self.t += 1000
        return self.t

    def sleep(self, s):
        self.t += int(s * 1e9)


def _both(tmp_path: Path, duration: float = 1.5) -> tuple[Path, Path]:
    sim = tmp_path / "sim.csv"
    assert main(["simulate", str(FIG5), "--out", str(sim), "--duration", str(duration)]) == 0
    run = tmp_path / "run.csv"
    vc = VirtualClock()
    code = Service(RunOptions(str(FIG5), out=str(run), duration_s=duration, live=False, stream=io.StringIO(),
                              err=io.StringIO(), status_socket=str(tmp_path / "s.sock"),
                              clock_ns=vc.now, sleep=vc.sleep)).run()
    assert code == 0
    return sim, run


def test_run_and_simulate_write_the_same_plain_csv(tmp_path):
    from mrctl.runlog.format import RUN_COLUMNS

    sim, run = _both(tmp_path)
    header = ",".join(RUN_COLUMNS)
    for path in (sim, run):
        assert path.read_text().split("\n", 1)[0] == header  # the header first: no comment line
        # what a plain CSV reader (pandas.read_csv, numpy) sees: every column, named
        data = np.genfromtxt(path, delimiter=",", names=True)
        assert data.dtype.names == RUN_COLUMNS
    a = np.genfromtxt(sim, delimiter=",", names=True)
    b = np.genfromtxt(run, delimiter=",", names=True)
    n = min(len(a), len(b))
    assert n >= 1500
    for c in SAME:  # the same number in the same column, to the log's 9 digits
        np.testing.assert_allclose(b[c][:n], a[c][:n], rtol=2e-8, atol=1e-12, equal_nan=True, err_msg=c)
    for d in (a, b):
        # F is the load cell as the controller received it: on the simulated bench
        # the plant's force of the tick before (no sensor noise in fig5); F_true is
        # the plant's force of this tick
        np.testing.assert_allclose(d["F"][1:], d["F_true"][:-1], rtol=2e-8, atol=1e-9)
        assert np.array_equal(d["k"], np.arange(len(d)))


def test_sidecar_describes_every_column_the_fault_bits_and_the_exit_code(tmp_path):
    from mrctl.core.safety import Fault
    from mrctl.runlog.format import RUN_COLUMNS

    sim, run = _both(tmp_path, 0.5)
    for path, command in ((sim, "simulate"), (run, "run")):
        side = json.loads(path.with_suffix(".json").read_text())
        assert side["command"] == command and side["csv"] == path.name
        assert side["exit_code"] == 0 and side["complete"] is True
        assert side["columns"] == list(RUN_COLUMNS)
        info = side["column_info"]
        assert list(info) == list(RUN_COLUMNS)
        for c in RUN_COLUMNS:
            assert set(info[c]) == {"unit", "meaning"} and len(info[c]["meaning"]) > 10, c
        assert info["F"]["unit"] == "N" and "load cell" in info["F"]["meaning"]
        assert info["t"]["unit"] == "s" and info["late_us"]["unit"] == "us"
        bits = side["fault_bits"]
        members = {f.name: int(f) for f in Fault if f.name not in ("NONE", "SAMPLE")}
        assert {k: v["value"] for k, v in bits.items()} == members
        assert all(len(v["meaning"]) > 10 for v in bits.values())
        assert set(side["exit_codes"]) == {"0", "1", "2", "3", "4", "5"}
        # provenance: what ran, with what
        assert side["config"]["inverse"]["law"] == "smooth" and side["mrctl_version"]
        assert side["I_max_A"] == 0.6 and side["rate_hz"] == 1000


def test_docs_describe_the_log_as_the_code_does():
    from mrctl.runlog.format import RUN_COLUMNS, RUN_MEANINGS, RUN_UNITS, columns_markdown

    text = (ROOT / "docs" / "runlog.md").read_text()
    block = text.split("<!-- BEGIN GENERATED: mrctl.runlog.format.columns_markdown -->\n", 1)[1]
    block = block.split("\n<!-- END GENERATED -->")[0]
    assert block == columns_markdown(), "docs/runlog.md is stale: python -m mrctl.runlog"
    for c in RUN_COLUMNS:
        assert f"| `{c}` | {RUN_UNITS[c] or '-'} | {RUN_MEANINGS[c]} |" in block

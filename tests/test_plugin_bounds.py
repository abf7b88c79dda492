"""What a plugin or a config may do at start-up and still get a clear
refusal (exit 2), never a silent exit 0, a hang or an internal error:
SystemExit at import (D13), an import that never returns (D19), a reset()
that raises (D15), a stream host the IDNA codec refuses (D14)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FIG5 = (ROOT / "config" / "experiments" / "fig5.yaml").read_text()

PLUGINS = {
    "exits_law.py": "raise SystemExit(0)\n",
    "hangs_law.py": "import time\ntime.sleep(3600)\n",
    "reset_raises_law.py": '''
from mrctl.laws.base import CurrentLaw


class Law(CurrentLaw):
    name = "reset_raises"
    params = {}

    def __init__(self, ctx):
        pass

    def reset(self, I0=0.0):
        raise RuntimeError("cannot reset me")

    def current(self, m, F_des):
        return 0.0
''',
    "reset_exits_law.py": '''
from mrctl.laws.base import CurrentLaw


class Law(CurrentLaw):
    name = "reset_exits"
    params = {}

    def __init__(self, ctx):
        pass

    def reset(self, I0=0.0):
        raise SystemExit(0)

    def current(self, m, F_des):
        return 0.0
''',
}


def _config(tmp_path: Path, law: str | None = None, extra: str = "") -> Path:
    for name, text in PLUGINS.items():
        (tmp_path / name).write_text(text)
    text = FIG5
    if law is not None:
        text = (text.replace("law: smooth", f"law: '{law}'")
                .replace("  eps_N_per_A: 3.0        # hold the current where dF/dI is below ~3 N/A\n", "")
                .replace("  max_slew_A_per_s: 50.0  # current-driver slew bound: 0.05 A per 1 ms tick\n", ""))
    p = tmp_path / "exp.yaml"
    p.write_text(text + extra)
    return p


def _mrctl(tmp_path: Path, *args: str, timeout: float = 60, **env: str) -> subprocess.CompletedProcess:
    e = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)]), **env)
    return subprocess.run([sys.executable, "-m", "mrctl", *args], cwd=tmp_path, env=e,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("cmd", ["check", "run"])
def test_a_plugin_raising_systemexit_at_import_is_refused(tmp_path, cmd):
    cfg = _config(tmp_path, "exits_law:Law")
    args = [cmd, str(cfg)] + (["--out", str(tmp_path / "r.csv"), "--duration", "0.2", "--quiet"] if cmd == "run" else [])
    r = _mrctl(tmp_path, *args)
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "inverse.law: cannot load 'exits_law:Law': SystemExit(0) raised at import" in r.stderr
    assert not (tmp_path / "r.csv").exists()


@pytest.mark.parametrize("cmd", ["check", "run"])
def test_a_plugin_import_that_never_returns_is_refused_in_time(tmp_path, cmd):
    cfg = _config(tmp_path, "hangs_law:Law")
    args = [cmd, str(cfg)] + (["--out", str(tmp_path / "r.csv"), "--duration", "0.2", "--quiet"] if cmd == "run" else [])
    t0 = time.monotonic()
    r = _mrctl(tmp_path, *args, timeout=30, MRCTL_PLUGIN_IMPORT_TIMEOUT_S="1")
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "its import did not finish within 1 s" in r.stderr
    assert time.monotonic() - t0 < 20
    assert not (tmp_path / "r.csv").exists()


def test_the_import_bound_is_a_refusal_in_process(tmp_path, monkeypatch):
    from mrctl.laws import registry

    _config(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("MRCTL_PLUGIN_IMPORT_TIMEOUT_S", "0.3")
    registry.REGISTRY.clear()
    info = registry.find_law("current", "hangs_law:Law")
    assert info.cls is None and "did not finish within 0.3 s" in info.error
    monkeypatch.setenv("MRCTL_PLUGIN_IMPORT_TIMEOUT_S", "10")  # a second wait would take 10 s
    t0 = time.monotonic()  # asked again: refused at once, no second thread waits on the hung import
    info = registry.find_law("current", "hangs_law:Law")
    assert "has not finished" in info.error and time.monotonic() - t0 < 5.0
    registry.REGISTRY.clear()


@pytest.mark.parametrize("law,raised", [("reset_raises_law:Law", "RuntimeError: cannot reset me"),
                                        ("reset_exits_law:Law", "SystemExit")])
@pytest.mark.parametrize("cmd", ["check", "run"])
def test_a_law_whose_reset_raises_is_a_config_error_naming_it(tmp_path, cmd, law, raised):
    cfg = _config(tmp_path, law)
    args = [cmd, str(cfg)] + (["--out", str(tmp_path / "r.csv"), "--duration", "0.2", "--quiet"] if cmd == "run" else [])
    r = _mrctl(tmp_path, *args)
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert f"inverse.law: '{law.split('_law')[0]}': reset() raised {raised}" in r.stderr
    assert "internal error" not in r.stderr
    assert "backend" not in r.stdout  # refused before the start line, i.e. before the link is made
    assert not (tmp_path / "r.csv").exists()


@pytest.mark.parametrize("cmd", ["check", "run"])
def test_a_stream_host_the_idna_codec_refuses_exits_2(tmp_path, cmd):
    cfg = _config(tmp_path, extra="stream: {url: 'udp://a..b:9870'}\n")
    args = [cmd, str(cfg)] + (["--out", str(tmp_path / "r.csv"), "--duration", "0.2", "--quiet"] if cmd == "run" else [])
    r = _mrctl(tmp_path, *args)
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "stream.url: host 'a..b': not a valid host name" in r.stderr
    r = _mrctl(tmp_path, "run", str(_config(tmp_path)), "--stream", "udp://a..b:9870", "--duration", "0.2", "--quiet")
    assert r.returncode == 2 and "not a valid host name" in r.stderr and "internal error" not in r.stderr

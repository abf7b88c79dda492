"""Careless input gets exit 2 and one clear line, before anything touches a device."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from fake_devices import Listener

from mrctl.cli import main

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"
TCP_EXP = (ROOT / "config" / "experiments" / "hil_modbus_tcp.yaml").read_text()


def _limits() -> None:  # a child that reads without bound must not take the shared machine down
    resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))


def mrctl(*args: str, timeout: float = 30.0, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    try:
        return subprocess.run([sys.executable, "-m", "mrctl", *args], cwd=cwd, capture_output=True, text=True,
                              timeout=timeout, preexec_fn=_limits,
                              env=dict(os.environ, PYTHONPATH=str(ROOT)))
    except subprocess.TimeoutExpired as exc:
        raise AssertionError(f"mrctl {' '.join(args)} still running after {timeout} s") from exc


# -- 4. --duration ------------------------------------------------------------------------
@pytest.mark.parametrize("value", ["-1", "nan", "inf", "0", "-inf"])
@pytest.mark.parametrize("cmd", ["run", "simulate"])
def test_duration_must_be_a_finite_number_above_zero(tmp_path, cmd, value):
    args = [cmd, str(FIG5), f"--duration={value}"]
    if cmd == "run":
        args += ["--quiet", "--status-socket", str(tmp_path / "s.sock")]
    r = mrctl(*args, timeout=20.0)
    assert r.returncode == 2, (r.returncode, r.stderr[-500:])
    assert "--duration" in r.stderr and "> 0" in r.stderr
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr
    assert "ticks" not in r.stdout  # nothing ran


# -- 5. a bad --out is refused before the link opens ------------------------------------------
@pytest.mark.parametrize("where", ["a directory", "under a file", "unwritable"])
def test_bad_out_is_exit_2_before_the_device_is_touched(tmp_path, capsys, where):
    dev = Listener()
    try:
        cfg = tmp_path / "exp.yaml"
        cfg.write_text(TCP_EXP.replace("port: 5020", f"port: {dev.port}"))
        if where == "a directory":
            out = tmp_path / "adir"
            out.mkdir()
        elif where == "under a file":
            (tmp_path / "plain").write_text("x")
            out = tmp_path / "plain" / "run.csv"
        else:
            out = Path("/proc/mrctl-test/run.csv")  # not creatable, even by root
        code = main(["run", str(cfg), "--out", str(out), "--quiet", "--duration", "0.5",
                     "--status-socket", str(tmp_path / "s.sock")])
        err = capsys.readouterr().err
        assert code == 2, err
        assert str(out) in err and "internal error" not in err
        assert dev.connections == 0
    finally:
        dev.close()


# -- 6. a config that is not text -------------------------------------------------------------
@pytest.mark.parametrize("cmd", ["check", "simulate", "run"])
def test_binary_config_is_a_clean_error(tmp_path, capsys, cmd):
    bad = tmp_path / "garbage.yaml"
    bad.write_bytes(bytes(range(256)) * 4)
    args = [cmd, str(bad)]
    if cmd == "run":
        args += ["--quiet", "--status-socket", str(tmp_path / "s.sock")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "garbage.yaml" in err and "UTF-8" in err and "Traceback" not in err


# -- 8. files the config points at: size-capped, device files refused --------------------------
def test_check_of_a_device_file_is_refused_at_once():
    r = mrctl("check", "/dev/zero", timeout=20.0)
    assert r.returncode == 2, r.stderr[-300:]
    assert "/dev/zero" in r.stderr and "not a regular file" in r.stderr


@pytest.mark.parametrize("key", ["parameters", "excitation", "demand"])
def test_config_pointing_at_a_device_file_is_refused(tmp_path, key):
    text = FIG5.read_text()
    if key == "parameters":
        text = text.replace("parameters: table1", "parameters: /dev/zero")
    elif key == "excitation":
        text = text.replace("excitation: {type: sine, amplitude_m: 0.010, frequency_hz: 1.0}",
                            "excitation: {type: file, path: /dev/zero}")
    else:
        text = text.replace("demand: {type: viscous, c_des: 500.0}", "demand: {type: file, path: /dev/zero}")
    cfg = tmp_path / "exp.yaml"
    cfg.write_text(text)
    r = mrctl("check", str(cfg), "--allow-outside-paths", timeout=20.0)  # past the containment: the device itself
    assert r.returncode == 2, r.stderr[-300:]
    assert "/dev/zero" in r.stderr and "not a regular file" in r.stderr and key in r.stderr


def test_oversized_parameters_file_is_refused(tmp_path, capsys):
    big = tmp_path / "params.yaml"
    with big.open("w") as fh:
        fh.write("# padding\n" * 1_000_000)  # ~10 MB of comments
        fh.write("Fc0: 1.0\n")
    cfg = tmp_path / "exp.yaml"
    cfg.write_text(FIG5.read_text().replace("parameters: table1", f"parameters: {big}"))
    assert main(["check", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "parameters" in err and "too large" in err

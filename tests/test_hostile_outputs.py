"""Outputs that must not land where they would: over an input, through a symlink mrctl did not create."""

from __future__ import annotations

import os
import socket
import stat
from pathlib import Path

import pytest
import yaml

from mrctl.cli import main
from mrctl.config import load_yaml
from mrctl.errors import BadInput
from mrctl.util.files import refuse_special

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"
T7 = ROOT / "config" / "experiments" / "labjack_t7.yaml"


# -- an output never replaces an input, --force or not, for every command -----------------------
def test_calibrate_never_writes_over_its_experiment(tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_bytes(T7.read_bytes())
    os.link(cfg, tmp_path / "hard.yaml")
    for out in ("c.yaml", "hard.yaml"):
        assert main(["calibrate", str(cfg), "--out", str(tmp_path / out), "--force"]) == 2
        assert "an input of this command" in capsys.readouterr().err
    assert cfg.read_bytes() == T7.read_bytes()


@pytest.mark.parametrize("argv", [
    lambda d: ["simulate", str(d / "x.yaml"), "--out", str(d / "x.yaml"), "--force"],
    lambda d: ["simulate", str(d / "x.yaml"), "--out", str(d / "e.csv"), "--force"],  # the excitation it names
    lambda d: ["run", str(d / "x.yaml"), "--out", str(d / "x.yaml"), "--force", "--duration", "0.1"],
    lambda d: ["sweep", str(d / "s.yaml"), "--out", str(d / "s.yaml")],
    lambda d: ["sweep", str(d / "s.yaml"), "--out", str(d / "x.yaml")],  # its base
    lambda d: ["report", str(d / "r.csv"), "--out", str(d / "r.json"), "--force"],  # the run's sidecar
], ids=["simulate-config", "simulate-series", "run-config", "sweep-file", "sweep-base", "report-sidecar"])
def test_no_command_writes_over_one_of_its_inputs(tmp_path, capsys, argv):
    data = load_yaml(FIG5)
    (tmp_path / "x.yaml").write_text(yaml.safe_dump({**data, "duration_s": 0.2}))
    assert main(["simulate", str(tmp_path / "x.yaml"), "--out", str(tmp_path / "r.csv"), "-q"]) == 0
    (tmp_path / "e.csv").write_text("t,x\n0,0\n0.1,0.001\n0.2,0\n")
    data["excitation"] = {"type": "file", "path": "e.csv"}
    (tmp_path / "x.yaml").write_text(yaml.safe_dump({**data, "duration_s": 0.2}))
    (tmp_path / "s.yaml").write_text("base: x.yaml\ngrid: {demand.c_des: [250]}\n")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    capsys.readouterr()
    assert main(argv(tmp_path)) == 2
    assert "an input of this command" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


# -- mrctl examples never follows a symlink it did not create ------------------------------------
@pytest.mark.parametrize("force", [False, True])
def test_examples_refuse_a_symlinked_folder_and_write_nothing_through_it(tmp_path, capsys, force):
    target = tmp_path / "elsewhere"
    target.mkdir()
    (target / "experiments").mkdir()
    (target / "experiments" / "fig5.yaml").write_text("precious\n")
    dest = tmp_path / "ex"
    dest.mkdir()
    (dest / "config").symlink_to(target)
    assert main(["examples", str(dest), *(["--force"] if force else [])]) == 2
    err = capsys.readouterr().err
    assert f"{dest / 'config'}: is a symlink" in err and "nothing written" in err
    assert sorted(p.name for p in target.rglob("*")) == ["experiments", "fig5.yaml"]
    assert (target / "experiments" / "fig5.yaml").read_text() == "precious\n"
    assert sorted(p.name for p in dest.iterdir()) == ["config"]  # nothing else written either


def test_examples_refuse_a_symlinked_dir_and_a_linked_file(tmp_path, capsys):
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to("real")
    assert main(["examples", str(tmp_path / "link")]) == 2
    assert "link: is a symlink" in capsys.readouterr().err and not any((tmp_path / "real").iterdir())
    dest = tmp_path / "ex"
    assert main(["examples", str(dest), "-q"]) == 0
    (tmp_path / "secret").write_text("keep\n")
    victim = dest / "config" / "experiments" / "fig5.yaml"
    victim.unlink()
    victim.symlink_to(tmp_path / "secret")
    assert main(["examples", str(dest), "--force"]) == 2
    assert "fig5.yaml: is a symlink" in capsys.readouterr().err
    assert (tmp_path / "secret").read_text() == "keep\n"


# -- --force replaces a file, never a device, FIFO, socket or directory ---------------------------
def test_refuse_special_names_dev_null_a_character_device():
    """The real /dev/null, looked at with lstat only (never opened, never a CLI --force at it):
    without root, the device case of the test below."""
    with pytest.raises(BadInput, match=r"^/dev/null: --out names a character device, not a regular file;"):
        refuse_special(["/dev/null"])


#: a device node takes root to make: as any other user the unit test above is the device case
SPECIAL = ["fifo", "socket", "directory"] + (["device"] if os.geteuid() == 0 else [])


@pytest.mark.parametrize("kind", SPECIAL)
@pytest.mark.parametrize("argv", [
    lambda d, o: ["simulate", str(FIG5), "--out", str(o), "--force", "--duration", "0.1", "-q"],
    lambda d, o: ["run", str(FIG5), "--out", str(o), "--force", "--duration", "0.1", "-q"],
    lambda d, o: ["calibrate", str(d / "t7.yaml"), "--out", str(o), "--force"],
    lambda d, o: ["report", str(d / "r.csv"), "--out", str(o), "--force"],
    lambda d, o: ["simulate", str(FIG5), "--out", str(d / "x.csv"), "--force", "--duration", "0.1", "-q"],
], ids=["simulate", "run", "calibrate", "report", "simulate-sidecar"])
def test_force_never_replaces_a_device_a_fifo_a_socket_or_a_directory(tmp_path, capsys, kind, argv):
    """As root, `run --out /dev/null --force` once replaced /dev/null with the run log (a clone of it here)."""
    (tmp_path / "t7.yaml").write_bytes(T7.read_bytes())
    assert main(["simulate", str(FIG5), "--out", str(tmp_path / "r.csv"), "--duration", "0.1", "-q"]) == 0
    victim = tmp_path / ("x.json" if "x.csv" in argv(tmp_path, tmp_path / "o")[3] else "o.png")
    if kind == "fifo":
        os.mkfifo(victim)
    elif kind == "socket":
        with socket.socket(socket.AF_UNIX) as s:
            s.bind(str(victim))  # the name stays a socket once closed
    elif kind == "device":
        os.mknod(victim, 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # what /dev/null is
    else:
        victim.mkdir()
    before = os.lstat(victim)
    capsys.readouterr()
    assert main(argv(tmp_path, victim)) == 2
    err = capsys.readouterr().err
    assert "not a regular file" in err or "is a directory" in err, err
    after = os.lstat(victim)
    assert (after.st_mode, after.st_ino, after.st_rdev) == (before.st_mode, before.st_ino, before.st_rdev)

"""Files a config names: one containment check for all of them, and errors that never quote a file.

Every path an experiment (parameters, calibration, plant.model.parameters,
series), a sweep (its base, a grid value naming a parameter set), a dataset
description or a replay sidecar names lies under the named file's folder
(or its config/ tree), --data-dir, or anywhere with --allow-outside-paths;
and an error names a key and a line, never a line of the file.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import yaml

from mrctl.cli import main
from mrctl.config import load_yaml

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"
#: what /etc/shadow looks like: YAML reads each line as a key
SHADOW = "root:$6$SECRETHASH:19000:0:99999:7:::\ndaemon:*:19000:0:99999:7:::\nlp:TOPSECRET:1:0:99999:7:::\n"


@pytest.fixture
def secret(tmp_path: Path) -> Path:
    p = tmp_path / "etc" / "shadow"
    p.parent.mkdir()
    p.write_text(SHADOW)
    return p


def _cfg(tmp_path: Path, **changes) -> Path:
    data = load_yaml(FIG5)
    data.update(changes)
    d = tmp_path / "lab"
    d.mkdir(exist_ok=True)
    p = d / "x.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def _no_echo(err: str) -> bool:
    return "SECRETHASH" not in err and "TOPSECRET" not in err and "daemon:" not in err


@pytest.mark.parametrize("changes", [
    lambda s: {"parameters": str(s)},
    lambda s: {"parameters": {"file": str(s), "F0": 3.0}},
    lambda s: {"calibration": str(s)},
    lambda s: {"plant": {"model": {"type": "bouc-wen", "parameters": str(s)}}},
    lambda s: {"plant": {"parameters": str(s)}},
], ids=["parameters", "parameters.file", "calibration", "plant.model.parameters", "plant.parameters"])
def test_a_file_key_outside_the_folder_is_refused_and_never_echoed(tmp_path, secret, capsys, changes):
    cfg = _cfg(tmp_path, **changes(secret))
    assert main(["check", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "outside" in err and "--allow-outside-paths" in err and _no_echo(err), err
    assert main(["check", str(cfg), "--allow-outside-paths"]) == 2  # read now: keys by their line, nothing quoted
    err = capsys.readouterr().err
    assert "<the key at line 1>" in err and "<the key at line 3>" in err and _no_echo(err), err


def test_a_named_files_values_are_described_not_quoted(tmp_path, capsys):
    cfg = _cfg(tmp_path, parameters="p.yaml")
    (cfg.parent / "p.yaml").write_text("F0: hunter2-secret\nlaws: also-secret\n")
    assert main(["check", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "F0: must be a finite number, got a string (14 characters)" in err
    assert "laws: a string (11 characters) not allowed" in err and "secret" not in err
    (cfg.parent / "p.yaml").write_text("F0: *topsecretalias\n")  # PyYAML would quote the alias it met
    assert main(["check", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "line 1, column 5: invalid YAML: found undefined alias" in err and "topsecret" not in err
    # the config itself is the user's own: its values are still quoted (briefly)
    cfg = _cfg(tmp_path, rate_hz="fast")
    assert main(["check", str(cfg)]) == 2
    assert "rate_hz: must be a number, got 'fast'" in capsys.readouterr().err


def test_a_config_tree_may_name_its_own_files(tmp_path):
    from mrctl.util.files import Fence, fence_root

    tree = tmp_path / "config"
    (tree / "experiments" / "robust").mkdir(parents=True)
    (tree / "plants").mkdir()
    assert fence_root(tree / "experiments" / "robust") == tree.resolve()
    assert fence_root(tmp_path / "lab") == (tmp_path / "lab").resolve()  # no config/ above: its own folder
    (tree / "plants" / "m.yaml").write_text((ROOT / "config" / "plants" / "table1_mismatched.yaml").read_text())
    data = load_yaml(FIG5)
    data["plant"] = {"parameters": "../../plants/m.yaml"}
    (tree / "experiments" / "robust" / "x.yaml").write_text(yaml.safe_dump(data))
    assert main(["check", str(tree / "experiments" / "robust" / "x.yaml")]) == 0
    # a symlink inside the tree to a file outside it is outside
    (tree / "plants" / "link.yaml").symlink_to(tmp_path / "outside.yaml")
    (tmp_path / "outside.yaml").write_text("F0: 3.0\n")
    ok, err = Fence.around(tree / "experiments").admit("../plants/link.yaml", tree / "experiments", "k")
    assert ok is None and "outside" in str(err)


def test_a_sweep_base_and_a_grid_value_stay_in_the_folder(tmp_path, secret, capsys):
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "base.yaml").write_text(yaml.safe_dump({**load_yaml(FIG5), "duration_s": 0.2}))
    s = lab / "s.yaml"
    s.write_text(f"base: {secret}\n")
    assert main(["check", str(s)]) == 2
    err = capsys.readouterr().err
    assert "base: " in err and "outside" in err and _no_echo(err)
    assert main(["sweep", str(s), "--out", str(lab / "r.csv"), "--allow-outside-paths", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "base (" in err and "<the key at line 2>" in err and _no_echo(err)
    assert not (lab / "r.csv").exists()
    # a grid value naming a parameter set: the row says why, not what the file holds
    s.write_text(yaml.safe_dump({"base": "base.yaml", "grid": {"plant.parameters": ["table1", str(secret)]}}))
    for extra, needle in (([], "outside"), (["--allow-outside-paths"], "<the key at line 1>")):
        out = lab / f"r{len(extra)}.csv"
        assert main(["sweep", str(s), "--out", str(out), "--no-progress", "--workers", "1", *extra]) == 0
        rows = list(csv.DictReader(out.open()))
        assert [r["status"] for r in rows] == ["ok", "invalid"] and needle in rows[1]["error"]
        assert _no_echo(out.read_text())


def test_a_replay_sidecar_cannot_choose_its_folder(tmp_path, secret, capsys):
    run = tmp_path / "runs" / "run.csv"
    run.parent.mkdir()
    assert main(["simulate", str(FIG5), "--duration", "0.2", "--out", str(run), "-q"]) == 0
    side = json.loads(run.with_suffix(".json").read_text())
    side["config"]["parameters"] = str(secret)
    side["config_file"] = str(secret.parent / "x.yaml")  # "my config lived beside the secret"
    run.with_suffix(".json").write_text(json.dumps(side))
    capsys.readouterr()
    assert main(["simulate", "--replay", str(run)]) == 2
    err = capsys.readouterr().err
    assert "outside" in err and "the run log's folder" in err and _no_echo(err)
    assert main(["simulate", "--replay", str(run), "--allow-outside-paths"]) == 2
    assert _no_echo(capsys.readouterr().err)


def test_a_data_file_named_by_a_description_is_admitted_by_the_same_check(tmp_path, secret, capsys):
    d = tmp_path / "ds"
    d.mkdir()
    (d / "ds.yaml").write_text("version: 1\nprotocol: broadband\ncolumns: {time: t, displacement: x, force: F, "
                               f"input: u}}\nsample_rate_hz: 1000\nfiles: [{secret}]\n")
    assert main(["identify", str(d / "ds.yaml"), "--out", str(d / "P.yaml"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "files[0].path" in err and "outside" in err and "--data-dir" in err and _no_echo(err)

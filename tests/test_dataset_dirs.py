"""Where a dataset's records are: its data_dir: key, or --data-dir over it."""

from __future__ import annotations

from pathlib import Path

import pytest

from mrctl.cli import main
from mrctl.config.dataset import load_dataset
from mrctl.util.schema import ConfigError

DESC = """version: 1
protocol: constant_input
columns: {{time: t, displacement: x, force: F}}
{data_dir}files:
  - {{path: rec/a.csv, level: 0.1}}
"""


@pytest.fixture
def lab(tmp_path):
    data = tmp_path / "lab" / "data"
    (data / "rec").mkdir(parents=True)
    (data / "rec" / "a.csv").write_text("t,x,F\n0,0,0\n0.001,0,0\n")
    descs = tmp_path / "descs"
    descs.mkdir()
    return tmp_path, data, descs


def test_records_resolve_against_data_dir_then_the_option(lab):
    tmp, data, descs = lab
    keyed = descs / "keyed.yaml"
    keyed.write_text(DESC.format(data_dir="data_dir: ../lab/data\n"))
    with pytest.raises(ConfigError) as e:  # its data_dir: key leaves the description's directory
        load_dataset(keyed)
    assert "--data-dir" in str(e.value) and "--allow-outside-paths" in str(e.value)
    assert load_dataset(keyed, allow_outside=True).files[0].path == str(data / "rec" / "a.csv")
    assert load_dataset(keyed, data).files[0].path == str(data / "rec" / "a.csv")  # confirmed by the option
    plain = descs / "plain.yaml"
    plain.write_text(DESC.format(data_dir=""))
    with pytest.raises(ConfigError) as e:
        load_dataset(plain)  # beside the description: not there
    assert "files[0].path" in str(e.value)
    assert load_dataset(plain, data).files[0].path == str(data / "rec" / "a.csv")
    elsewhere = tmp / "copy"
    (elsewhere / "rec").mkdir(parents=True)
    (elsewhere / "rec" / "a.csv").write_text("t,x,F\n0,0,0\n0.001,0,0\n")
    assert load_dataset(keyed, elsewhere).files[0].path == str(elsewhere / "rec" / "a.csv")  # option wins
    with pytest.raises(ConfigError) as e:
        load_dataset(keyed, tmp / "nope")
    assert "--data-dir" in str(e.value) and "nope" in str(e.value)
    keyed.write_text(DESC.format(data_dir="data_dir: ../missing\n"))
    with pytest.raises(ConfigError) as e:
        load_dataset(keyed)
    assert "data_dir" in str(e.value) and "missing" in str(e.value)


def test_identify_data_dir_errors_are_exit_2(lab, capsys):
    tmp, data, descs = lab
    d = descs / "d.yaml"
    d.write_text(DESC.format(data_dir=""))
    assert main(["identify", "--dataset", str(d), "--data-dir", str(tmp / "nope"), "-o", str(tmp / "p.yaml")]) == 2
    assert "--data-dir" in capsys.readouterr().err
    assert main(["identify", str(tmp / "r.csv"), "--data-dir", str(data), "-o", str(tmp / "p.yaml")]) == 2
    assert "--data-dir is for --dataset" in capsys.readouterr().err

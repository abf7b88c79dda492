"""The dataset description: every error with its key path, and reading a lab's files.

Each rejection names the key to fix (``files[1].use[0]``, ``columns.force``)
or, for the data itself, the file, column and line; nothing invalid reaches
the fit, and the CLI reports each as one line with exit code 2.
"""

from __future__ import annotations

import copy
import re
from pathlib import Path

import numpy as np
import pytest

from mrctl.cli import main
from mrctl.config.dataset import dataset_markdown, load_dataset, validate_dataset
from mrctl.offline.identify import IdentificationError, identify_dataset
from mrctl.offline.identify.records import read_records
from mrctl.util.schema import ConfigError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def data_dir(tmp_path):
    t = np.arange(200) * 0.01
    rows = "\n".join(f"{a:.3f},{np.sin(a):.6f},{np.cos(a):.6f},{2 * np.cos(a):.4f},0.5" for a in t)
    (tmp_path / "rec.csv").write_text("time,pos_mm,vel,force,cmd\n" + rows + "\n")
    (tmp_path / "rec2.csv").write_text("time,pos_mm,vel,force,cmd\n" + rows + "\n")
    return tmp_path


def good(**changes):
    d = {"version": 1, "protocol": "broadband", "input": "voltage",
         "columns": {"time": "time", "displacement": {"name": "pos_mm", "scale": 0.001}, "force": "force",
                     "input": "cmd"},
         "files": [{"path": "rec.csv"}]}
    for path, value in changes.items():
        node = d
        keys = path.split(".")
        for k in keys[:-1]:
            node = node[int(k)] if isinstance(node, list) else node.setdefault(k, {})
        if value is _DELETE:
            del node[keys[-1]]
        else:
            node[keys[-1]] = value
    return d


_DELETE = object()


def _errors(data, base):
    with pytest.raises(ConfigError) as ei:
        validate_dataset(copy.deepcopy(data), base, "ds.yaml")
    return ei.value.errors


def test_a_good_description_fills_defaults(data_dir):
    ds = validate_dataset(good(), data_dir)
    assert ds.protocol == "broadband" and ds.input == "voltage"
    assert ds.columns.displacement.scale == 0.001 and ds.columns.force.scale == 1.0
    assert ds.files[0].role == "fit" and ds.files[0].path == str((data_dir / "rec.csv").resolve())
    assert ds.model.offset and ds.model.lag and not ds.model.inertia
    assert ds.holdout.fraction is None and ds.fit.starts == 3


@pytest.mark.parametrize("change, expect", [
    ({"colour": "red"}, "colour: unknown key"),
    ({"protocol": "sweep"}, "protocol: 'sweep' not allowed (allowed: constant_input, broadband)"),
    ({"protocol": _DELETE}, "protocol: missing required key"),
    ({"version": 2}, "version: 2 out of range"),
    ({"input": "amps"}, "input: 'amps' not allowed (allowed: current, voltage)"),
    ({"columns.force": _DELETE}, "columns.force: missing required key"),
    ({"columns.force": {"nme": "F"}}, "columns.force.nme: unknown key"),
    ({"columns.force": {"name": "F", "scale": 0}}, "columns.force.scale: must not be 0"),
    ({"columns.force": {"name": "F", "index": -1}}, "columns.force.index: -1 out of range"),
    ({"columns.force": 3}, "columns.force: must be a mapping"),
    ({"columns.speed": "v"}, "columns.speed: unknown key"),
    ({"format.type": "xlsx"}, "format.type: 'xlsx' not allowed (allowed: csv, mat)"),
    ({"sample_rate_hz": 0}, "sample_rate_hz: 0 out of range"),
    ({"holdout.fraction": 0.95}, "holdout.fraction: 0.95 out of range"),
    ({"fit.starts": 0}, "fit.starts: 0 out of range"),
    ({"model.lag": "yes"}, "model.lag: must be true or false"),
    ({"files": "rec.csv"}, "files: must be a list of records"),
    ({"files": [{"path": "rec.csv", "role": "test"}]}, "files[0].role: 'test' not allowed (allowed: fit, holdout)"),
    ({"files": [{"path": "rec.csv", "use": [[2.0, 1.0]]}]}, "files[0].use[0]: need t0 < t1"),
    ({"files": [{"path": "rec.csv", "use": [[0, 1, 2]]}]}, "files[0].use[0]: must be [t0, t1]"),
    ({"files": [{"path": "rec.csv", "exclude": "all"}]}, "files[0].exclude: must be a list of [t0, t1] windows"),
    ({"files": [{"path": "rec.csv", "use": [[0, "x"]]}]}, "files[0].use[0][1]: must be a number"),
    ({"files": [{"path": "missing.csv"}]}, "files[0].path: no such file"),
    ({"files": [{"path": "nodir/rec.csv"}]}, "files[0].path: no such directory"),
    ({"files": [{"path": "rec.csv"}, {"path": "rec.csv"}]}, "files: record names must be unique; repeated: rec"),
    ({"files": [{"path": "rec.csv", "role": "holdout"}]}, "files: every record has role: holdout"),
    ({"files": []}, "files: no records"),
    ({"columns.displacement": None, "columns.velocity": None}, "columns: need displacement or velocity"),
    ({"columns.time": None}, "columns.time: no time column; give one or set sample_rate_hz"),
    ({"columns.input": None}, "columns.input: broadband identification needs the input column"),
    ({"files": [{"path": "rec.csv", "level": 1.0}]}, "files[0]: level/levels are for constant_input"),
    ({"columns.displacement": None, "columns.velocity": "vel"}, "model.stiffness: needs columns.displacement"),
])
def test_every_description_error_names_its_key(data_dir, change, expect):
    errs = _errors(good(**change), data_dir)
    assert any(expect in e for e in errs), errs


@pytest.mark.parametrize("files, expect", [
    ([{"path": "rec.csv"}], "files[0]: no input level: give level, levels, or columns.input"),
    ([{"path": "rec.csv", "level": 1.0, "levels": [{"from_s": 0, "to_s": 1, "value": 1}]}],
     "files[0]: give level (whole file) or levels (per segment), not both"),
    ([{"path": "rec.csv", "levels": [{"from_s": 1, "to_s": 0.5, "value": 1}]}], "files[0].levels[0]: need from_s < to_s"),
    ([{"path": "rec.csv", "levels": [{"from_s": 0, "to_s": 1, "value": 1}, {"from_s": 0.5, "to_s": 2, "value": 2}]}],
     "files[0].levels[1]: overlaps the segment before it"),
    ([{"path": "rec.csv", "levels": [{"from_s": 0, "to_s": 1}]}], "files[0].levels[0].value: missing required key"),
    ([{"path": "rec.csv", "levels": []}], "files[0].levels: must be a non-empty list"),
])
def test_constant_input_level_errors(data_dir, files, expect):
    errs = _errors(good(protocol="constant_input", files=files, **{"columns.input": None}), data_dir)
    assert any(expect in e for e in errs), errs


def test_manifest_errors(data_dir):
    base = good(protocol="constant_input", files=[], **{"columns.input": None})
    base["manifest"] = {"path": "nothere.csv", "level": "V"}
    assert any("manifest.path: no such file" in e for e in _errors(base, data_dir))
    base["manifest"] = {"path": "rec.csv"}
    assert any("manifest.level: missing required key" in e for e in _errors(base, data_dir))
    bb = good()
    bb["manifest"] = {"path": "rec.csv", "level": "cmd"}
    assert any("manifest: only for constant_input" in e for e in _errors(bb, data_dir))


def test_all_errors_at_once(data_dir):
    errs = _errors(good(protocol="sweep", input="amps", **{"fit.starts": 0}), data_dir)
    assert len(errs) >= 3


# -- reading the data --------------------------------------------------------------
def _write_ds(tmp: Path, data: dict) -> Path:
    import yaml

    p = tmp / "ds.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


@pytest.mark.parametrize("csv_text, expect", [
    ("time,pos,vel,force,cmd\n0,0,0,0,0\n0.01,0,0,0,0\n0.02,0,0,0,0\n", "no column 'pos_mm' (columns.displacement)"),
    ("time,pos_mm,vel,force,cmd\n0,0,0,0,0\n0.01,0,x,1,0\n0.02,0,0,0,0\n0.03,0,0,0,0\n",
     None),  # vel is not read (no velocity column described): fine
    ("time,pos_mm,vel,force,cmd\n0,0,0,0,0\n0.01,0,0,oops,0\n0.02,0,0,0,0\n0.03,0,0,0,0\n",
     "line 3: column force (field 4) is not a number"),
    ("time,pos_mm,vel,force,cmd\n0,0,0,0,0\n0.01,0,0,nan,0\n0.02,0,0,0,0\n0.03,0,0,0,0\n",
     "column 'force' (columns.force) is not finite at sample 1"),
    ("time,pos_mm,vel,force,cmd\n0,0,0,0,0\n0.01,0,0,1,0\n0.01,0,0,0,0\n0.03,0,0,0,0\n",
     "time is not strictly increasing at sample 2"),
    ("time,pos_mm,vel,force,cmd\n0,0,0,0,0\n0.01,0,0,1,0\n0.02,0,0,0,0\n0.5,0,0,0,0\n0.51,0,0,0,0\n",
     "not uniformly sampled"),
    ("time,pos_mm,vel,force,cmd\n0,0,0,0,0\n", "1 data row(s); far too short"),
    ("", "empty file"),
])
def test_csv_problems_name_file_column_and_line(tmp_path, csv_text, expect):
    (tmp_path / "rec.csv").write_text(csv_text)
    ds = load_dataset(_write_ds(tmp_path, good()))
    if expect is None:
        assert read_records(ds)[0].F.size == 4
        return
    with pytest.raises(IdentificationError, match=re.escape(expect)):
        read_records(ds)


def test_csv_with_quoted_header_trailing_comma_and_sample_rate(tmp_path):
    """The NEES layout: quoted names, a trailing empty column, a rounded time column."""
    t = np.round(np.arange(50) / 3004.8, 4)
    rows = "\n".join(f"{a},{0.001 * k},{k},0.5," for k, a in enumerate(t))
    (tmp_path / "r.csv").write_text('"t","D","F","Y",\n' + rows + "\n")
    ds = load_dataset(_write_ds(tmp_path, good(files=[{"path": "r.csv"}], sample_rate_hz=3004.8,
                                               columns={"time": "t", "displacement": {"name": "D", "scale": 0.01},
                                                        "force": "F", "input": "Y"})))
    rec = read_records(ds)[0]
    assert rec.fs == 3004.8 and np.allclose(np.diff(rec.t), 1 / 3004.8)
    assert rec.x[2] == pytest.approx(2e-5) and rec.F[3] == 3.0 and rec.u[0] == 0.5


def test_mat_files(tmp_path):
    from scipy.io import savemat

    n = 60
    savemat(tmp_path / "r.mat", {"Tout": (np.arange(n) * 0.01)[:, None], "dist": np.arange(n)[:, None] * 1.0,
                                 "x_F": np.column_stack([np.zeros(n), np.ones(n), 2 * np.ones(n) + np.arange(n)]),
                                 "label": np.array(["abc"])})
    cols = {"time": "Tout", "displacement": {"name": "dist", "scale": 0.001}, "force": {"name": "x_F", "index": 2}}
    ds = load_dataset(_write_ds(tmp_path, good(protocol="constant_input", files=[{"path": "r.mat", "level": 0.5}],
                                               columns=cols)))
    rec = read_records(ds)[0]
    assert rec.F[0] == 2.0 and rec.x[10] == pytest.approx(0.01) and rec.level == 0.5 and rec.fs == pytest.approx(100)
    for force, expect in ((("forc",), "no variable 'forc' (columns.force); the file has: Tout, dist, x_F"),
                          (("x_F",), "is 60×3: set columns.force.index"),
                          (("x_F", 5), "columns.force.index 5 is out of range"),
                          (("label",), "is not numeric")):
        cols["force"] = {"name": force[0], **({"index": force[1]} if len(force) > 1 else {})}
        ds = load_dataset(_write_ds(tmp_path, good(protocol="constant_input", columns=cols,
                                                   files=[{"path": "r.mat", "level": 0.5}])))
        with pytest.raises(IdentificationError, match=re.escape(expect)):
            read_records(ds)


def test_mat_v73_and_garbage(tmp_path):
    # a MATLAB 7.3 (HDF5) header: 116 bytes of text, 8 of subsystem offset, version 0x0200, 'IM'
    head = b"MATLAB 7.3 MAT-file, Platform: GLNXA64".ljust(116, b" ") + b"\0" * 8 + b"\x00\x02IM"
    (tmp_path / "r.mat").write_bytes(head + b"\0" * 512)
    cols = {"time": "Tout", "displacement": "dist", "force": "forc"}
    ds = load_dataset(_write_ds(tmp_path, good(protocol="constant_input", columns=cols,
                                               files=[{"path": "r.mat", "level": 0.5}])))
    with pytest.raises(IdentificationError, match="v7.3 .HDF5."):
        read_records(ds)
    (tmp_path / "r.mat").write_bytes(b"\x01\x02 not a mat file" * 10)
    with pytest.raises(IdentificationError, match="not a readable MATLAB .mat file"):
        read_records(ds)


def test_manifest_lists_files_and_levels(tmp_path, data_dir):
    (data_dir / "manifest.csv").write_text("file,input_V\nrec.csv,0.5\nrec2.csv,1.5\n")
    d = good(protocol="constant_input", files=[], manifest={"path": "manifest.csv", "level": "input_V"},
             **{"columns.input": None})
    recs = read_records(validate_dataset(d, data_dir))
    assert [(r.name, r.level) for r in recs] == [("rec", 0.5), ("rec2", 1.5)]
    (data_dir / "manifest.csv").write_text("file,input_V\nrec.csv,half\n")
    with pytest.raises(IdentificationError, match=r"line 2: the level \(column 'input_V'\) is not a number"):
        read_records(validate_dataset(d, data_dir))
    (data_dir / "manifest.csv").write_text("file,input_V\nother.csv,1\n")
    with pytest.raises(IdentificationError, match="line 2: no such file"):
        read_records(validate_dataset(d, data_dir))


def test_windows_that_leave_nothing_and_unknown_holdout_names(data_dir):
    p = _write_ds(data_dir, good(files=[{"path": "rec.csv", "use": [[50.0, 60.0]]}]))
    with pytest.raises(IdentificationError, match="its use/exclude windows leave no samples"):
        identify_dataset(p)
    p = _write_ds(data_dir, good())
    with pytest.raises(IdentificationError, match="--holdout: no record named nope"):
        identify_dataset(p, holdout="nope")
    with pytest.raises(IdentificationError, match="every record would be held out"):
        identify_dataset(p, holdout="rec")
    with pytest.raises(IdentificationError, match="--holdout: 2 out of range"):
        identify_dataset(p, holdout="2")


def test_cli_reports_description_errors_as_exit_2(data_dir, capsys):
    p = _write_ds(data_dir, good(files=[{"path": "nowhere/rec.csv"}], protocol="sweep"))
    out = data_dir / "p.yaml"
    assert main(["identify", "--dataset", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "protocol: 'sweep' not allowed" in err and "files[0].path: no such directory" in err
    assert "Traceback" not in err and not out.exists()
    # a .yaml argument is a dataset too; run CSVs and --dataset together are refused
    assert main(["identify", str(p), "--out", str(out)]) == 2
    assert "protocol" in capsys.readouterr().err
    assert main(["identify", "a.csv", "--dataset", str(p), "--out", str(out)]) == 2
    assert "not both" in capsys.readouterr().err


def test_shipped_descriptions_validate_or_name_the_missing_data():
    for f in sorted((ROOT / "config" / "datasets").glob("*.yaml")):
        try:
            ds = load_dataset(f, allow_outside=True)  # they point at the shared data, outside config/
        except ConfigError as exc:  # the data is not on this machine: the error names the directory
            assert all("no such directory" in e or "no such file" in e for e in exc.errors), exc.errors
            continue
        assert ds.protocol in ("broadband", "constant_input")


def test_reference_table_in_the_docs_is_current():
    text = (ROOT / "docs" / "identification.md").read_text()
    block = text.split("<!-- BEGIN GENERATED: mrctl.config.dataset.dataset_markdown -->\n", 1)[1]
    block = block.split("\n<!-- END GENERATED -->")[0]
    assert block == dataset_markdown(), "docs/identification.md is stale: run python -m mrctl.config.dataset"

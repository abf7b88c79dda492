"""The one CSV reader behind run logs, truth logs and excitation/demand series."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mrctl.util.csvtable import CsvError, read_table


def _write(tmp_path: Path, text: str | bytes) -> Path:
    p = tmp_path / "t.csv"
    p.write_bytes(text.encode() if isinstance(text, str) else text)
    return p


def test_columns_by_name_others_unparsed_physical_line_numbers(tmp_path: Path) -> None:
    p = _write(tmp_path, "# a comment\n\nt,fault,x\n0,none,1.5\n# mid-file comment\n0.001,OVERCURRENT,nan\n")
    tab = read_table(p, ["x", "t", "absent"])
    assert list(tab.columns) == ["t", "x"]  # header order; absent ones left out
    assert tab.columns["x"][0] == 1.5 and np.isnan(tab.columns["x"][1])
    assert list(tab.lines) == [4, 6] and tab.header == ["t", "fault", "x"]
    with pytest.raises(CsvError, match=r"line 4: column fault is not a number: 'none'"):
        read_table(p)  # all columns: the text column now counts


@pytest.mark.parametrize("text, message", [
    ("", "empty file"),
    ("# only\n\n", "empty file"),
    ("t,x\n0,1\n0.001\n", r"line 3 has 1 fields, the header has 2"),
    ("t,x\n0,1\n0.001,2,3\n", r"line 3 has 3 fields, the header has 2"),
    ("t,x,x\n0,1,2\n", r"column\(s\) x appear more than once in the header \(line 1\)"),
    ("t,x\n0,\n", r"line 2: column x is not a number: ''"),
])
def test_errors_name_file_line_and_column(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(CsvError, match=message) as info:
        read_table(_write(tmp_path, text))
    assert str(info.value).startswith(str(tmp_path / "t.csv"))


def test_required_columns_and_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(CsvError, match=r"missing required column\(s\) F, I; found: t, x"):
        read_table(_write(tmp_path, "t,x\n0,1\n"), require=("t", "F", "I"))
    with pytest.raises(CsvError, match="no such file"):
        read_table(tmp_path / "nope.csv")
    with pytest.raises(CsvError, match="is a directory"):
        read_table(tmp_path)
    with pytest.raises(CsvError, match="not a text"):
        read_table(_write(tmp_path, b"t,x\n\xff\xfe,1\n"))


def test_torn_last_line_dropped_only_when_asked(tmp_path: Path) -> None:
    p = _write(tmp_path, "t,x\n0,1\n0.001,2\n0.0")
    assert list(read_table(p, torn_last_line_ok=True).columns["t"]) == [0.0, 0.001]
    with pytest.raises(CsvError, match="line 4 has 1 fields"):
        read_table(p)
    p = _write(tmp_path, "t,x\n0,1\n0.001,2")  # complete, but no final newline
    assert list(read_table(p).columns["t"]) == [0.0, 0.001]
    assert list(read_table(p, torn_last_line_ok=True).columns["t"]) == [0.0]
    assert read_table(_write(tmp_path, "t,x\n")).columns["t"].shape == (0,)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(alphabet=st.sampled_from(list("tx,#\n .0123456789eE+-naif\r\t")), max_size=120),
       torn=st.booleans(), wanted=st.sampled_from([None, ("t",), ("t", "x")]))
def test_fuzz_any_text_gives_a_table_or_a_csv_error(tmp_path: Path, text: str, torn: bool, wanted) -> None:
    p = _write(tmp_path, text)
    try:
        tab = read_table(p, wanted, torn_last_line_ok=torn)
    except CsvError as exc:
        assert str(exc).startswith(str(p))
        return
    for col in tab.columns.values():
        assert col.dtype == float and col.shape == tab.lines.shape

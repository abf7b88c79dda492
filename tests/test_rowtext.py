"""The run log's row formatter: the compiled path writes what Python's ``%``
writes, byte for byte (mrctl/runlog/rowtext.py, _rowtext.c).

Python's ``'%.9g' % value`` is the contract (mrctl/runlog/format.py). These
tests compare the formatter this suite's build loads (C where compiled,
the ``%`` twin under ``MRCTL_PURE_PYTHON=1``) against ``%`` itself, on
awkward values and on random bit patterns; tests/test_builds.py compares
whole simulate CSVs across the builds.
"""

from __future__ import annotations

import math
import sys
from array import array

import numpy as np
import pytest

from mrctl.build import COMPILED, pure_requested, tick_build
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS
from mrctl.runlog.rowtext import RowFormatter, compiled_available, precisions

TINY = 5e-324
#: values each path must write as '%' does
AWKWARD = [
    math.nan, -math.nan, math.inf, -math.inf, 0.0, -0.0, TINY, -TINY, 2.2250738585072014e-308,
    sys.float_info.max, -sys.float_info.max, 1e-300, 1e300, 1e-15, 1e-14, 1e30, 1e31, 1e22, 1e23,
    # integers in float columns (counters, tick indices, fault bits), below and above 10^P
    1.0, -1.0, 7.0, 255.0, 123456789.0, 999999999.0, 1e9, 1234567890.0, 9999999999.0, 1e10, 2.0 ** 53,
    2.0 ** 63, 1e17, 1e18,
    # ties at 9 and 10 digits (round half to even), and near ties
    1234567885.0, 1234567895.0, 12345678905.0, 0.125, 2.5, 0.5, 1.5, 1.0000000005, 1.0000000015,
    # around powers of ten, where the exponent changes
    9.9999999995, 9.99999999949, 0.099999999995, 99999999.95, 999999999.5, 9999999999.5,
    0.001, 0.0001, 0.00001, 0.000099999999995, 1e-5 * (1 + 2 ** -52), 123456.789, 0.1, 0.2, 0.3,
    # a log's usual values: times, forces, currents, positions
    0.001 * 12345, 604800.0, 604799.999, 0.6, 0.05000000000000002, 0.15830094173201317, -437.21962011,
    0.0099999999, 3.14159265358979, -2.718281828459045,
]
AWKWARD += [math.nextafter(v, d) for v in (1.0, 10.0, 1e8, 1e9, 1e-4, 1e-5, 1e10, 0.5) for d in (0.0, math.inf)]
AWKWARD += [-v for v in AWKWARD]


def _reference(values: list[float], fmts: list[str]) -> bytes:
    ncols = len(fmts)
    row = ",".join(fmts) + "\n"
    return "".join(row % tuple(values[i:i + ncols]) for i in range(0, len(values), ncols)).encode("ascii")


def test_the_formatter_is_compiled_exactly_when_the_tick_is():
    """One build, all or nothing (setup.py): the C formatter with the mypyc tick."""
    f = RowFormatter(RUN_COLUMNS, RUN_FORMATS)
    if pure_requested():
        assert not compiled_available() and not f.compiled
    else:
        assert f.compiled == compiled_available() == (tick_build() == COMPILED)


@pytest.mark.parametrize("prec", [9, 10, 1, 2, 6, 12, 13, 17])
def test_awkward_values_are_written_as_percent_g_writes_them(prec):
    fmt = f"%.{prec}g"
    f = RowFormatter(["a"], fmt, require_core=False)
    col = np.array(AWKWARD)
    assert f.columns_text([col], 0, len(col)) == _reference(AWKWARD, [fmt])
    assert f.rows(array("d", AWKWARD), 0, len(AWKWARD)) == _reference(AWKWARD, [fmt])


@pytest.mark.parametrize("prec", [9, 10, 3, 12])
def test_random_bit_patterns_and_magnitudes_are_written_as_percent_g_writes_them(prec):
    rng = np.random.default_rng(prec)
    n = 100_000
    bits = np.frombuffer(rng.integers(0, 2 ** 63, n, dtype=np.uint64).tobytes(), dtype=float)
    mags = rng.lognormal(0.0, 12.0, n) * rng.choice([-1.0, 1.0], n)
    scale = 10.0 ** rng.integers(0, 8, n)
    decimals = np.round(rng.uniform(-1e4, 1e4, n) * scale) / scale  # short decimals, like k·dt
    ties = (rng.integers(10 ** (prec - 1), 10 ** prec, n) * 10 + 5) / 10.0 ** rng.integers(0, 12, n)
    fmt = f"%.{prec}g"
    f = RowFormatter(["a"], fmt, require_core=False)
    for col in (bits, mags, decimals, ties):
        assert f.columns_text([col], 0, n) == _reference(col.tolist(), [fmt])


def test_a_run_log_block_in_both_layouts_and_with_the_gil_released():
    rng = np.random.default_rng(1)
    n = 3000
    cols = [rng.normal(0.0, 10.0 ** rng.integers(-6, 4), n) for _ in RUN_COLUMNS]
    cols[6] = np.arange(n, dtype=float)  # k
    cols[11][::7] = math.nan  # late_us
    cols[3][::11] = 1e-320  # a subnormal: CPython's conversion, with the GIL taken back
    cols[4][::13] = 1234567885.0  # a tie: the same
    f = RowFormatter(RUN_COLUMNS, RUN_FORMATS)
    fmts = [RUN_FORMATS[c] for c in RUN_COLUMNS]
    rows = np.column_stack(cols)
    want = _reference(rows.ravel().tolist(), fmts)
    assert f.columns_text(cols, 0, n) == want
    assert f.columns_text(cols, 0, n, release_gil=True) == want
    packed = array("d", rows.ravel().tolist())
    assert f.rows(packed, 0, n) == want
    assert f.rows(packed, 0, n, release_gil=True) == want
    lines = want.split(b"\n")
    assert f.rows(packed, 17, 5) == b"\n".join(lines[17:22]) + b"\n"
    assert f.columns_text(cols, 2990, 10) == b"\n".join(lines[2990:3000]) + b"\n"
    assert f.rows(packed, n, 0) == b"" == f.columns_text(cols, 0, 0)


def test_rows_outside_the_buffer_and_wrong_buffers_are_refused():
    f = RowFormatter(RUN_COLUMNS, RUN_FORMATS)
    packed = array("d", [0.5] * (3 * len(RUN_COLUMNS)))
    for row0, nrows in ((0, 4), (2, 2), (-1, 1), (0, -1)):
        with pytest.raises(IndexError):
            f.rows(packed, row0, nrows)
    cols = [np.zeros(3)] * len(RUN_COLUMNS)
    with pytest.raises(IndexError):
        f.columns_text(cols, 1, 3)
    with pytest.raises(ValueError):
        f.columns_text(cols[:-1], 0, 1)
    if f.compiled:  # the Python twin reads any sequence of numbers; C only float64 buffers
        with pytest.raises(TypeError):
            f.columns_text([array("f", [0.5] * 3)] * len(RUN_COLUMNS), 0, 3)


def test_formats_other_than_percent_g_take_the_python_twin():
    assert precisions(["%.9g", "%.10g"]) == (9, 10)
    for fmts in (["%r"], ["%.9g", "%.6f"], ["%.18g"], ["%.0g"], ["%9g"]):
        assert precisions(fmts) is None
    f = RowFormatter(["a", "b"], "%r", require_core=False)
    assert not f.compiled
    assert f.rows(array("d", [0.1, -0.0, math.nan, 1e300]), 0, 2) == b"0.1,-0.0\nnan,1e+300\n"
    with pytest.raises(ValueError):
        RowFormatter(["a", "a"], "%.9g", require_core=False)  # row_format's checks


def test_the_header_is_the_column_names():
    assert RowFormatter(RUN_COLUMNS, RUN_FORMATS).header() == (",".join(RUN_COLUMNS) + "\n").encode()

"""``mrctl check SWEEP.yaml``: the sweep file's schema, then its space, without building every point.

A sweep of ten million points cannot be checked point by point (each is a
config to build and validate). What can fail is a value: a grid value, or
a draw. So each grid value is checked on every base, the other axes at a
value that passes, and each random key at both ends of its range (a
normal's mean ± 4 standard deviations), the other keys at draw 0: a few
configs per value, whatever the size. A failing grid value's points are
counted exactly (they are the product of the other axes); a draw that
fails at an end is named with the value, since how many draws reach it
depends on the draws.
"""

from __future__ import annotations

import math
from typing import Any

from mrctl.config import ConfigError, validate_experiment
from mrctl.sweep.points import draws, resolve
from mrctl.sweep.spec import Sweep, load_sweep

#: distinct errors listed at most
SHOWN = 5
#: a normal draw is checked this many standard deviations either side of its mean
NORMAL_SPAN = 4.0


def _error(sweep: Sweep, base: str, picks: list[int], drawn: dict[str, tuple[str, float]]) -> str | None:
    """The config's error (None if it validates) with the grid at ``picks`` and the draws ``drawn``."""
    overrides: list[tuple[str, Any]] = []
    for ax, k in zip(sweep.axis_values, picks):
        overrides += ax[k][1]
    try:
        config = resolve(sweep, base, overrides, drawn)
        validate_experiment(config, sweep.bases[base].parent, fence=sweep.fence)
    except ConfigError as exc:
        return "; ".join(exc.errors)
    except Exception as exc:  # noqa: BLE001 - what the point's row would say (mrctl.sweep.point)
        return f"{type(exc).__name__}: {exc}"
    return None


def _grid_errors(sweep: Sweep, base: str, drawn: dict[str, tuple[str, float]]
                 ) -> tuple[dict[tuple[int, int], str], int]:
    """(axis, value) → error of each grid value that fails on ``base``, the
    other axes at a value that passes (found in a second pass if the first
    value of an axis fails); and how many configs were checked."""
    sizes = [len(ax) for ax in sweep.axis_values]
    ref = [0] * len(sizes)
    failed: dict[tuple[int, int], str] = {}
    checked = 0
    for _ in range(2):
        failed = {}
        for j, size in enumerate(sizes):
            for k in range(size):
                checked += 1
                err = _error(sweep, base, ref[:j] + [k] + ref[j + 1:], drawn)
                if err is not None:
                    failed[(j, k)] = err
        better = [next((k for k in range(size) if (j, k) not in failed), ref[j]) if (j, ref[j]) in failed else ref[j]
                  for j, size in enumerate(sizes)]
        if better == ref:
            break
        ref = better
    if not sizes:
        checked += 1
        err = _error(sweep, base, [], drawn)
        if err is not None:
            failed[(-1, 0)] = err
    return failed, checked


def _draw_ends(sweep: Sweep) -> list[tuple[str, float, dict[str, tuple[str, float]]]]:
    """(key, value, draws) for each random key at each end of its range, the others at draw 0."""
    zero = draws(sweep, 0)
    out = []
    for key, (kind, a, b) in sweep.random.items():
        ends = (a - NORMAL_SPAN * b, a + NORMAL_SPAN * b) if kind.endswith("normal") else (a, b)
        for x in ends:
            out.append((key, x, {**zero, key: (kind, x)}))
    return out


def check_sweep(path: str, *, allow_outside: bool = False) -> int:
    """0 when the file is valid (points that will fail are listed, not an error: they become failed rows);
    the sweep file's own errors raise ConfigError (exit 2)."""
    sweep = load_sweep(path, allow_outside=allow_outside)
    sizes = [len(ax) for ax in sweep.axis_values]
    n = sweep.random_n or 1
    per_base = n * math.prod(sizes)
    zero = draws(sweep, 0) if sweep.random else {}
    bad: dict[str, list[int]] = {}  # error → [points, first point]
    invalid = 0
    checked = 0
    for b, base in enumerate(sweep.bases):
        failed, n_checked = _grid_errors(sweep, base, zero)
        checked += n_checked
        passing = n * math.prod(size - sum(1 for (a, _k) in failed if a == j) for j, size in enumerate(sizes))
        invalid += per_base - passing if (-1, 0) not in failed else per_base
        for (j, k), err in failed.items():
            count = per_base // sizes[j] if j >= 0 else per_base
            first = b * per_base + (k * _stride(sizes, j) * n if j >= 0 else 0)
            entry = bad.setdefault(err, [0, first])
            entry[0] += count
            entry[1] = min(entry[1], first)
    print(f"{path}: {sweep.size()} points ({', '.join(sweep.axes) or 'no axes'}; metrics {', '.join(sweep.metrics)})")
    for err, (count, first) in sorted(bad.items(), key=lambda e: -e[1][0])[:SHOWN]:
        print(f"{path}: warning: {count} point(s) will fail (first: point {first}): {err}")
    for key, x, drawn in _draw_ends(sweep) if sweep.random else []:
        err = _error(sweep, next(iter(sweep.bases)), [0] * len(sizes), drawn)
        checked += 1
        if err is not None:
            print(f"{path}: warning: draws of random.{key} near {x:g} will fail: {err}")
    print(f"{path}: checked {checked} configs (every grid value on every base, each draw's range at its ends), "
          "not each point: a point's config is built when it runs")
    print(f"{path}: OK" + (f" ({invalid} point(s) invalid: rows with their error)" if invalid else ""))
    return 0


def _stride(sizes: list[int], j: int) -> int:
    """Grid cells between two values of axis ``j`` (the axes after it vary faster)."""
    return math.prod(sizes[j + 1:])

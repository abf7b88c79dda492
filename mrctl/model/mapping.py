"""Parameter sets from plain mappings (a parameters file's, an experiment's inline set).

Not on the hot path (:mod:`mrctl.model.params` is compiled; these run once
at load): every value is checked, and a ``ValueError`` names the offending
key, which the config layer turns into a user-facing error with the file
and key path.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

from mrctl.model.params import (TABLE_BENCH_NAMES, TABLE_HYS_NAMES, TABLE_I, TABLE_NAMES, LuGreParams, ThetaTable,
                                extra_problems)

__all__ = ["params_from_mapping", "table_from_mapping"]


def params_from_mapping(data: Any) -> LuGreParams:
    """Build a parameter set from a mapping of spec names, Table I filling gaps.

    Raises ``ValueError`` naming the offending key; the config layer turns it
    into a user-facing error with the file and key path."""
    if not isinstance(data, dict):
        raise ValueError(f"parameters must be a mapping of {', '.join(LuGreParams.all_names())}")
    known = set(LuGreParams.all_names())
    values: dict[str, float] = {}
    table = table_from_mapping(data.get("laws", "paper"), data.get("table"))
    for key, value in data.items():
        if key in ("laws", "table"):
            continue
        if key not in known:
            raise ValueError(f"{key}: unknown parameter (expected one of {', '.join(LuGreParams.all_names())})")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{key}: must be a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ValueError(f"{key}: must be finite, got {value!r}")
        values[key] = float(value)
    out = replace(TABLE_I.with_overrides(**values), table=table)
    problems = extra_problems(out)
    if problems:
        raise ValueError("; ".join(problems))
    return out


def table_from_mapping(laws: Any, data: Any) -> ThetaTable | None:
    """``laws:`` and ``table:`` of a parameters mapping: None for the paper's
    laws, else a checked :class:`ThetaTable`. ``ValueError`` lists every
    problem with its key path (the input strictly increasing, Θ finite and,
    σ1 aside, > 0)."""
    if laws == "paper" or laws is None:
        if data is not None:
            raise ValueError("table: given but laws is not 'table' (set laws: table, or drop the table)")
        return None
    if laws != "table":
        raise ValueError(f"laws: {laws!r} not allowed (paper: laws (6)-(11); table: interpolated per-level values)")
    if not isinstance(data, dict):
        raise ValueError("table: laws: table needs a mapping with input and " + ", ".join(TABLE_NAMES)
                         + " (lists of numbers, one per level)")
    problems: list[str] = []
    names = TABLE_NAMES + TABLE_BENCH_NAMES + TABLE_HYS_NAMES
    for key in data:
        if key != "input" and key not in names:
            problems.append(f"table.{key}: unknown (expected input, {', '.join(names)})")
    bench = [k for k in TABLE_BENCH_NAMES if k in data]
    if len(bench) == 1:
        problems.append(f"table.{bench[0]}: give both {' and '.join(TABLE_BENCH_NAMES)}, or neither")
    hys = [k for k in TABLE_HYS_NAMES if k in data]
    if hys and (len(hys) == 1 or len(bench) != 2):
        problems.append(f"table.{hys[0]}: give both {' and '.join(TABLE_HYS_NAMES)}, with "
                        f"{' and '.join(TABLE_BENCH_NAMES)}, or neither")
    cols: list[tuple[float, ...]] = []
    for key in (("input",) + TABLE_NAMES + (TABLE_BENCH_NAMES if len(bench) == 2 else ())
                + (TABLE_HYS_NAMES if len(hys) == 2 else ())):
        raw = data.get(key)
        if not isinstance(raw, list) or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in raw):
            problems.append(f"table.{key}: must be a list of numbers (one per level)")
            cols.append(())
        else:
            cols.append(tuple(float(x) for x in raw))
    if problems:
        raise ValueError("; ".join(problems))
    table = ThetaTable(cols[0], tuple(cols[1:]))
    problems = table.problems()
    if problems:
        raise ValueError("; ".join(problems))
    return table

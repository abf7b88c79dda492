"""A sweep's points, made one at a time from their index.

A point is its index: the grid cell (bases × grid axes, the last axis
varying fastest) and the draw (``index % n``) follow from it, and its
config (the base's YAML, its values applied, every parameter set read into
plain numbers) is built only when it is asked for (:func:`point`), so a
sweep of ten million points costs no more memory than one of ten, and
``mrctl check`` looks at the space (:mod:`mrctl.sweep.check`) without
building it. Why plain data: the point's hash (resumption) and a Dask
worker both see exactly what will run.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np

from mrctl.config import ConfigError
from mrctl.config.params import params_check, params_input_kind
from mrctl.config.plants import bouc_wen_from_data
from mrctl.util.schema import read_named_yaml, short_repr

if TYPE_CHECKING:
    from mrctl.sweep.spec import Sweep

__all__ = ["Point", "Unresolved", "point", "expand", "config_hash", "resolve", "cell_of", "PARAM_SETS",
           "DISCRIMINATORS"]

#: key paths that hold a parameter set (their entries can be varied by key path)
PARAM_SETS = ("parameters", "plant.parameters", "plant.model.parameters")
#: a section's discriminator: setting it to another value starts the section afresh
DISCRIMINATORS = ("law", "type")


@dataclass
class Point:
    """One simulation of a sweep: its values (the table's columns) and its config."""

    index: int
    values: dict[str, Any]
    seed: int | None
    config: dict[str, Any]
    base_dir: str
    hash: str = ""
    fence: str | None = None  # the root files it names must lie under (None: anywhere)

    def task(self, metrics: tuple[str, ...]) -> dict[str, Any]:
        """What a worker receives: plain data only."""
        return {"index": self.index, "config": self.config, "base_dir": self.base_dir, "metrics": list(metrics),
                "hash": self.hash, "fence": self.fence}


@dataclass
class Unresolved:
    """A point whose values cannot even be applied (a factor on a missing
    key, a parameter set that cannot be read): a failed row at once."""

    index: int
    values: dict[str, Any]
    error: str

    @property
    def hash(self) -> str:
        return f"unresolved-{self.index}"


# --------------------------------------------------------------------------
# Applying values by key path
def get_path(d: dict[str, Any], key: str) -> Any:
    for part in key.split("."):
        if not isinstance(d, dict) or part not in d:
            return None
        d = d[part]
    return d


def _set(d: dict[str, Any], key: str, value: Any) -> None:
    parts = key.split(".")
    for part in parts[:-1]:
        nxt = d.get(part)
        if not isinstance(nxt, dict):
            nxt = d[part] = {}
        d = nxt
    last = parts[-1]
    if last in DISCRIMINATORS and d.get(last) is not None and d.get(last) != value:
        d.clear()  # another law or type: its keys are not the old one's
    d[last] = copy.deepcopy(value)


def _in_param_set(key: str) -> bool:
    return any(key.startswith(s + ".") for s in PARAM_SETS)


def _absolute(key: str, value: Any, sweep_dir: Path) -> Any:
    """A file a sweep file names for a parameter set is relative to the sweep file."""
    if key in PARAM_SETS and isinstance(value, str) and value != "table1" and not Path(value).is_absolute():
        return str(sweep_dir / value)
    if key in PARAM_SETS and isinstance(value, dict) and isinstance(value.get("file"), str):
        return {**value, "file": str(_absolute(key, value["file"], sweep_dir))}
    return value


def _resolve_param_sets(sweep: "Sweep", data: dict[str, Any], base_dir: Path, needed: set[str]) -> None:
    """Parameter sets as plain numbers (Table I, a file, a file with overrides → a mapping); every
    file admitted by the sweep's fence and read once per sweep (a named set is the same every point)."""
    fence = sweep.fence
    for key in ("parameters", "plant.parameters"):
        raw = get_path(data, key)
        if raw is None and key == "plant.parameters":
            if not any(n.startswith("plant.parameters.") for n in needed):
                continue
            raw = copy.deepcopy(data.get("parameters", "table1"))  # the simulated damper runs the law's set
        cache_key = (key, str(base_dir), raw) if isinstance(raw, str) else None
        if cache_key is not None and cache_key in sweep.cache:
            _set(data, key, sweep.cache[cache_key])
            continue
        kind, _f = params_input_kind(raw, base_dir, fence)
        if kind != "current":
            if isinstance(raw, str) and not Path(raw).is_absolute():
                _set(data, key, str(base_dir / raw))
            continue  # a voltage set keeps its file (the file says what it takes)
        params, errors = params_check(base_dir, fence)(raw, key)
        if errors:
            raise ConfigError(errors)
        if cache_key is not None:
            sweep.cache[cache_key] = params.as_dict()
        _set(data, key, params.as_dict())
    bw = get_path(data, "plant.model.parameters")
    if isinstance(bw, str):
        cache_key = ("plant.model.parameters", str(base_dir), bw)
        if cache_key not in sweep.cache:
            got, errors = read_named_yaml(bw, base_dir, fence, "plant.model.parameters",
                                          lambda full, d: bouc_wen_from_data(d).as_dict())
            if got is None:
                raise ConfigError(errors)
            sweep.cache[cache_key] = got
        _set(data, "plant.model.parameters", sweep.cache[cache_key])


def _draw(kind: str, a: float, b: float, rng: np.random.Generator) -> float:
    base = kind.removeprefix("factor_")
    if base == "uniform":
        return float(rng.uniform(a, b))
    if base == "normal":
        return float(rng.normal(a, b))
    return float(math.exp(rng.uniform(math.log(a), math.log(b))))


def draws(sweep: "Sweep", i: int) -> dict[str, tuple[str, float]]:
    """Draw ``i``'s values: the same for every grid cell (common random numbers)."""
    rng = np.random.default_rng([sweep.random_seed, i])
    return {key: (kind, _draw(kind, a, b, rng)) for key, (kind, a, b) in sweep.random.items()}


def axis_values(sweep: "Sweep") -> list[list[tuple[Any, list[tuple[str, Any]]]]]:
    """Per grid axis, its values as (column label, overrides)."""
    axes: list[list[tuple[Any, list[tuple[str, Any]]]]] = []
    for key, values in sweep.grid.items():
        if isinstance(values, list):
            axes.append([(v, [(key, v)]) for v in values])
        else:
            axes.append([(name, list((o or {}).items())) for name, o in values.items()])
    return axes


def cell_of(sweep: "Sweep", cell: int) -> tuple[str, dict[str, Any], list[tuple[str, Any]]]:
    """(base name, column values, overrides) of grid cell ``cell``: bases
    outermost, then the axes in file order, the last fastest (as
    ``itertools.product``)."""
    axes = sweep.axis_values
    picks: list[int] = []
    for ax in reversed(axes):
        cell, k = divmod(cell, len(ax))
        picks.append(k)
    picks.reverse()
    base = list(sweep.bases)[cell]
    cols: dict[str, Any] = {"base": base} if len(sweep.bases) > 1 else {}
    overrides: list[tuple[str, Any]] = []
    for key, ax, k in zip(sweep.grid, axes, picks):
        label, ov = ax[k]
        cols[key] = label
        overrides += ov
    return base, cols, overrides


def config_hash(config: dict[str, Any], base_dir: str, metrics: tuple[str, ...]) -> str:
    """The point's key for resumption: what runs and what is kept."""
    text = json.dumps({"config": config, "base_dir": base_dir, "metrics": list(metrics)}, sort_keys=True,
                      separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def resolve(sweep: "Sweep", base: str, overrides: list[tuple[str, Any]],
            drawn: dict[str, tuple[str, float]]) -> dict[str, Any]:
    """The point's experiment as plain data: base, then overrides (discriminators first), parameter
    sets read, then values inside parameter sets and the random draws."""
    base_dir = sweep.bases[base].parent
    sweep_dir = Path(sweep.source).parent
    data = copy.deepcopy(sweep.raw_bases[base])
    outer = [(k, v) for k, v in overrides if not _in_param_set(k)]
    inner = [(k, v) for k, v in overrides if _in_param_set(k)]
    for key, value in sorted(outer, key=lambda kv: kv[0].split(".")[-1] not in DISCRIMINATORS):
        _set(data, key, _absolute(key, value, sweep_dir))
    _resolve_param_sets(sweep, data, base_dir, {k for k, _ in overrides} | set(drawn))
    for key, value in inner:
        _set(data, key, value)
    for key, (kind, x) in drawn.items():
        if kind.startswith("factor_"):
            old = get_path(data, key)
            if isinstance(old, bool) or not isinstance(old, (int, float)):
                raise ConfigError([f"random.{key}: a factor needs a number there, the point has {short_repr(old)}"])
            x = old * x
        _set(data, key, x)
    return data


def point(sweep: "Sweep", index: int) -> Point | Unresolved:
    """Point ``index`` (0 ≤ index < :meth:`Sweep.size`), its config built now."""
    n = sweep.random_n or 1
    cell, i = divmod(index, n)
    base, cols, overrides = cell_of(sweep, cell)
    drawn = draws(sweep, i) if sweep.random else {}
    values = {**cols, **{k: x for k, (_kind, x) in drawn.items()}}
    try:
        config = resolve(sweep, base, overrides, drawn)
    except ConfigError as exc:
        return Unresolved(index, values, "; ".join(exc.errors))
    values.update({k: get_path(config, k) for k in drawn})  # a factor's column: the value it gave
    base_dir = str(sweep.bases[base].parent)
    p = Point(index, values, i if sweep.random else None, config, base_dir, fence=sweep.fence.to_text())
    p.hash = config_hash(config, base_dir, sweep.metrics)
    return p


def expand(sweep: "Sweep", start: int = 0) -> Iterator[Point | Unresolved]:
    """Every point from ``start`` on, in order, each built as it is taken."""
    for index in range(start, sweep.size()):
        yield point(sweep, index)

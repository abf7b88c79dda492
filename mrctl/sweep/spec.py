"""The sweep file: its schema, and what a point of it is.

A sweep file (``config/sweeps/*.yaml``, docs/sweeps.md) names a ``base``
experiment (or several, by name), a ``grid`` of key paths and their values,
``random`` draws combined with the grid as a product, and the ``metrics``
kept per point. Every file it names (its bases, the parameter sets its grid
names, and theirs) lies under its folder (its ``config/`` tree) unless
``--allow-outside-paths`` (:class:`mrctl.util.files.Fence`). A point is its
index; its config, the base's YAML with its values applied and every
parameter set read into plain numbers, is built when it runs
(:mod:`mrctl.sweep.points`), so a worker on another machine needs mrctl,
not the files, and a sweep's size costs no memory.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from mrctl.config import ConfigError, Custom, Num, Str, validate_experiment, validate_fields
from mrctl.config.experiment import experiment_schema
from mrctl.sweep.metrics import DEFAULT_METRICS, METRICS
from mrctl.sweep.points import DISCRIMINATORS, PARAM_SETS, Point, Unresolved, axis_values, expand, point  # noqa: F401
from mrctl.util.files import Fence
from mrctl.util.schema import check_num, key_repr, load_yaml_lines, quoting, read_named_yaml, short_repr

#: distributions of ``random:`` (absolute, or relative to the point's value with ``factor_``)
DISTRIBUTIONS = ("uniform", "normal", "log_uniform")
#: the most points a sweep may have: ~9 ms of CPU each, ten million are 25 CPU-hours (two cores:
#: half a day) and a results table of ~3 GB; docs/sweeps.md, "Size"
MAX_POINTS = 10_000_000


@dataclass
class Sweep:
    """A validated sweep file."""

    source: str
    name: str
    bases: dict[str, Path]
    grid: dict[str, Any]
    random_n: int | None
    random_seed: int
    random: dict[str, tuple[str, float, float]]
    metrics: tuple[str, ...]
    raw_bases: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: where the files it names must lie (its folder, unless --allow-outside-paths)
    fence: Fence = field(default_factory=Fence.anywhere)
    #: parameter sets read from files, by (key, base folder, value): read once per sweep
    cache: dict[Any, Any] = field(default_factory=dict, repr=False)

    @property
    def axes(self) -> list[str]:
        """The table's value columns, in order."""
        cols = ["base"] if len(self.bases) > 1 else []
        return cols + list(self.grid) + list(self.random)

    @functools.cached_property
    def axis_values(self) -> list[list[tuple[Any, list[tuple[str, Any]]]]]:
        """Per grid axis, its values as (column label, overrides)
        (:func:`mrctl.sweep.points.axis_values`), built once: every point picks from them."""
        return axis_values(self)

    def size(self) -> int:
        n = len(self.bases) * (self.random_n or 1)
        for values in self.grid.values():
            n *= len(values)
        return n

    def point(self, index: int) -> Point | Unresolved:
        """Point ``index``, its config built now (:func:`mrctl.sweep.points.point`)."""
        return point(self, index)

    def points(self, start: int = 0) -> Iterator[Point | Unresolved]:
        """Every point from ``start`` on, each built as it is taken."""
        return expand(self, start)


def _top_keys() -> tuple[str, ...]:
    return tuple(experiment_schema(Path(".")))


def _key_path(key: Any, where: str) -> list[str]:
    if not isinstance(key, str) or not key or any(not part for part in key.split(".")):
        return [f"{where}: {short_repr(key)} is not a key path (dotted names, e.g. demand.c_des)"]
    top = key.split(".")[0]
    if top not in _top_keys():
        return [f"{where}.{key_repr(key)}: {key_repr(top)!r} is not an experiment key "
                f"(allowed: {', '.join(_top_keys())})"]
    return []


def _base_check(base_dir: Path, fence: Fence):
    """``base``: experiment files (admitted by ``fence``, read without quoting
    them, each validated with the same fence): (name → path, name → data)."""
    def one(value: Any, path: str) -> tuple[tuple[Path, dict[str, Any]] | None, list[str]]:
        if not isinstance(value, str) or not value:
            return None, [f"{path}: must be an experiment file path, got {short_repr(value)}"]

        def read(full: Path, data: Any) -> tuple[Path, dict[str, Any]]:
            validate_experiment(data, full.parent, str(full), fence=fence)
            return full, data

        return read_named_yaml(value, base_dir, fence, path, read)

    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        named = value if isinstance(value, dict) else {"base": value}
        if not named:
            return None, [f"{path}: must name at least one experiment"]
        out, errors = {}, []
        for name, v in named.items():
            got, errs = one(v, f"{path}.{key_repr(name)}" if isinstance(value, dict) else path)
            errors += errs
            if got is not None:
                out[str(name)] = got
        return (out if not errors else None), errors

    return check


def _grid_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return {}, []
    if not isinstance(value, dict):
        return None, [f"{path}: must be a mapping of key path → list of values (or name → overrides)"]
    errors: list[str] = []
    for key, values in value.items():
        where = f"{path}.{key_repr(key)}"
        if isinstance(values, list):
            errors += _key_path(key, path)
            if not values:
                errors.append(f"{where}: must list at least one value")
        elif isinstance(values, dict):  # a named axis: each value a set of overrides
            if not values:
                errors.append(f"{where}: must name at least one value")
            for name, overrides in values.items():
                if overrides is None:
                    continue
                if not isinstance(overrides, dict):
                    errors.append(f"{where}.{key_repr(name)}: must be a mapping of key path → value, got "
                                  f"{short_repr(overrides)}")
                    continue
                for k in overrides:
                    errors += _key_path(k, f"{where}.{key_repr(name)}")
        else:
            errors.append(f"{where}: must be a list of values, or a mapping of name → {{key path: value}}; "
                          f"got {short_repr(values)}")
    return value, errors


def _dist(value: Any, where: str) -> tuple[tuple[str, float, float] | None, list[str]]:
    kinds = DISTRIBUTIONS + tuple(f"factor_{d}" for d in DISTRIBUTIONS)
    if not isinstance(value, dict) or len(value) != 1:
        return None, [f"{where}: must be one distribution, e.g. {{uniform: [lo, hi]}} (one of {', '.join(kinds)})"]
    (kind, args), = value.items()
    if kind not in kinds:
        return None, [f"{where}.{key_repr(kind)}: unknown distribution (one of {', '.join(kinds)})"]
    if (not isinstance(args, list) or len(args) != 2 or any(isinstance(a, bool) or not isinstance(a, (int, float))
                                                          or not math.isfinite(a) for a in args)):
        return None, [f"{where}.{kind}: must be two finite numbers, got {short_repr(args)}"]
    a, b = float(args[0]), float(args[1])
    if kind.endswith("normal"):
        if b < 0:
            return None, [f"{where}.{kind}: [mean, std]: std must be >= 0, got {b:g}"]
    elif not a <= b:
        return None, [f"{where}.{kind}: [lo, hi] needs lo <= hi, got {short_repr(args)}"]
    if kind.endswith("log_uniform") and a <= 0:
        return None, [f"{where}.{kind}: log-uniform needs lo > 0, got {a:g}"]
    return (kind, a, b), []


def _random_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return None, []
    if not isinstance(value, dict):
        return None, [f"{path}: must be a mapping with n, seed and key path → distribution"]
    errors: list[str] = []
    n, errs = check_num(Num(integer=True, min=1, max=MAX_POINTS), value.get("n"), f"{path}.n")
    errors += errs if "n" in value else [f"{path}.n: missing required key"]
    seed, errs = check_num(Num(integer=True, min=0, max=2**63 - 1), value.get("seed", 0), f"{path}.seed")
    errors += errs
    dists: dict[str, tuple[str, float, float]] = {}
    for key, v in value.items():
        if key in ("n", "seed"):
            continue
        errs = _key_path(key, path)
        if not errs:
            d, errs = _dist(v, f"{path}.{key_repr(key)}")
            if d is not None:
                dists[key] = d
        errors += errs
    if not dists and not errors:
        errors.append(f"{path}: name at least one key path → distribution")
    return (n, seed or 0, dists), errors


def _metrics_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return DEFAULT_METRICS, []
    if not isinstance(value, list) or not value:
        return None, [f"{path}: must be a non-empty list of metric names (one of {', '.join(METRICS)})"]
    errors = [f"{path}[{i}]: {short_repr(m)} unknown (one of {', '.join(METRICS)})" for i, m in enumerate(value)
              if m not in METRICS]
    if len(set(value)) != len(value):
        errors.append(f"{path}: lists a metric twice")
    return tuple(value), errors


def sweep_schema(base_dir: Path, fence: Fence | None = None) -> dict[str, Any]:
    """What a sweep file may say (docs/sweeps.md); the files it names admitted by ``fence``."""
    fence = fence if fence is not None else Fence.around(base_dir, what="the sweep")
    return {
        "version": Num(default=1, integer=True, min=1, max=1, doc="sweep format version (1)"),
        "name": Str(default=None, optional=True, doc="sweep name (figure titles)"),
        "description": Str(default=None, optional=True, doc="free text"),
        "base": Custom(_base_check(base_dir, fence), doc="experiment file, or name → experiment file (an axis 'base')"),
        "grid": Custom(_grid_check, default=None,
                       doc="key path → list of values; or an axis name → {value name: {key path: value}}"),
        "random": Custom(_random_check, default=None,
                         doc="n draws (seed) of key path → distribution; with the grid as a product"),
        "metrics": Custom(_metrics_check, default=None, doc="figures kept per point"),
    }


def is_sweep_file(data: Any) -> bool:
    """A sweep file has ``base:`` where an experiment has ``version``/``safety``."""
    return isinstance(data, dict) and "base" in data


def load_sweep(path: str | Path, *, allow_outside: bool = False) -> Sweep:
    """Load and validate a sweep file; ConfigError lists every problem with its key path.
    The files it names (and theirs) lie under its folder unless ``allow_outside``."""
    p = Path(path)
    data, lines = load_yaml_lines(p)
    if not isinstance(data, dict):
        raise ConfigError([f"sweep: must be a mapping, got {type(data).__name__}"], str(p))
    fence = Fence.around(p.parent, allow_outside, what="the sweep")
    with quoting(lines=lines):
        node, errors = validate_fields(sweep_schema(p.parent, fence), data, "")
    if errors:
        raise ConfigError(errors, str(p))
    rnd = node.random
    sweep = Sweep(source=str(p), name=node.name or p.stem, bases={k: f for k, (f, _d) in node.base.items()},
                  grid=dict(node.grid), random_n=rnd[0] if rnd else None, random_seed=rnd[1] if rnd else 0,
                  random=rnd[2] if rnd else {}, metrics=node.metrics, fence=fence)
    sweep.raw_bases = {k: d for k, (_f, d) in node.base.items()}
    clash = [a for a in sweep.random if a in sweep.grid]
    if clash:
        raise ConfigError([f"random.{a}: also a grid axis; vary a key one way" for a in clash], str(p))
    if sweep.size() > MAX_POINTS:
        raise ConfigError([f"grid × random: {sweep.size()} points, more than {MAX_POINTS}"], str(p))
    return sweep


def sweep_markdown() -> str:
    """The sweep file's keys, its distributions and its metrics as markdown (docs/sweeps.md)."""
    from mrctl.sweep.metrics import METRIC_DOCS
    from mrctl.util.schema import schema_markdown

    dists = ", ".join(f"`{d}`" for d in DISTRIBUTIONS + tuple(f"factor_{d}" for d in DISTRIBUTIONS))
    return (schema_markdown(sweep_schema(Path("."))) + "\n\nDistributions of `random:`: " + dists
            + " (`uniform`/`log_uniform`: [lo, hi]; `normal`: [mean, std]; `factor_…`: the point's value times "
              "the draw).\n\n| metric | meaning |\n|---|---|\n"
            + "\n".join(f"| `{m}` | {d} |" for m, d in METRIC_DOCS.items()))

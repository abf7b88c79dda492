"""The sweep file: its schema, and its expansion into points of plain data.

A sweep file (``config/sweeps/*.yaml``, docs/sweeps.md) names a ``base``
experiment (or several, by name), a ``grid`` of key paths and their values,
``random`` draws combined with the grid as a product, and the ``metrics``
kept per point. Every point is the base's YAML with its values applied and
every parameter set read into plain numbers, so a worker on another machine
needs mrctl, not the files (:func:`expand`). Why plain data: the point's hash
(resumption) and a Dask worker both see exactly what will run.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from mrctl.config import ConfigError, Custom, Num, Str, load_yaml, validate_experiment, validate_fields
from mrctl.util.schema import check_num
from mrctl.config.experiment import experiment_schema
from mrctl.config.params import params_check, params_input_kind
from mrctl.config.plants import load_bouc_wen_file
from mrctl.sweep.metrics import DEFAULT_METRICS, METRICS

#: key paths that hold a parameter set (their entries can be varied by key path)
PARAM_SETS = ("parameters", "plant.parameters", "plant.model.parameters")
#: a section's discriminator: setting it to another value starts the section afresh
DISCRIMINATORS = ("law", "type")
#: distributions of ``random:`` (absolute, or relative to the point's value with ``factor_``)
DISTRIBUTIONS = ("uniform", "normal", "log_uniform")
MAX_POINTS = 10_000_000


@dataclass
class Point:
    """One simulation of a sweep: its values (the table's columns) and its config."""

    index: int
    values: dict[str, Any]
    seed: int | None
    config: dict[str, Any]
    base_dir: str
    hash: str = ""

    def task(self, metrics: tuple[str, ...]) -> dict[str, Any]:
        """What a worker receives: plain data only."""
        return {"index": self.index, "config": self.config, "base_dir": self.base_dir, "metrics": list(metrics),
                "hash": self.hash}


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

    @property
    def axes(self) -> list[str]:
        """The table's value columns, in order."""
        cols = ["base"] if len(self.bases) > 1 else []
        return cols + list(self.grid) + list(self.random)

    def size(self) -> int:
        n = len(self.bases) * (self.random_n or 1)
        for values in self.grid.values():
            n *= len(values)
        return n


def _top_keys() -> tuple[str, ...]:
    return tuple(experiment_schema(Path(".")))


def _key_path(key: Any, where: str) -> list[str]:
    if not isinstance(key, str) or not key or any(not part for part in key.split(".")):
        return [f"{where}: {key!r} is not a key path (dotted names, e.g. demand.c_des)"]
    top = key.split(".")[0]
    if top not in _top_keys():
        return [f"{where}.{key}: {top!r} is not an experiment key (allowed: {', '.join(_top_keys())})"]
    return []


def _base_check(base_dir: Path):
    def one(value: Any, path: str) -> tuple[Path | None, list[str]]:
        if not isinstance(value, str) or not value:
            return None, [f"{path}: must be an experiment file path, got {value!r}"]
        full = Path(value) if Path(value).is_absolute() else base_dir / value
        if not full.is_file():
            return None, [f"{path}: no such file: {full}"]
        try:
            validate_experiment(load_yaml(full), full.parent, str(full))
        except ConfigError as exc:
            return None, [f"{path} ({full}): {e}" for e in exc.errors]
        return full, []

    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if isinstance(value, dict):
            if not value:
                return None, [f"{path}: must name at least one experiment"]
            out, errors = {}, []
            for name, v in value.items():
                out[str(name)], errs = one(v, f"{path}.{name}")
                errors += errs
            return out, errors
        full, errors = one(value, path)
        return {"base": full}, errors

    return check


def _grid_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return {}, []
    if not isinstance(value, dict):
        return None, [f"{path}: must be a mapping of key path → list of values (or name → overrides)"]
    errors: list[str] = []
    for key, values in value.items():
        where = f"{path}.{key}"
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
                    errors.append(f"{where}.{name}: must be a mapping of key path → value, got {overrides!r}")
                    continue
                for k in overrides:
                    errors += _key_path(k, f"{where}.{name}")
        else:
            errors.append(f"{where}: must be a list of values, or a mapping of name → {{key path: value}}; "
                          f"got {values!r}")
    return value, errors


def _dist(value: Any, where: str) -> tuple[tuple[str, float, float] | None, list[str]]:
    kinds = DISTRIBUTIONS + tuple(f"factor_{d}" for d in DISTRIBUTIONS)
    if not isinstance(value, dict) or len(value) != 1:
        return None, [f"{where}: must be one distribution, e.g. {{uniform: [lo, hi]}} (one of {', '.join(kinds)})"]
    (kind, args), = value.items()
    if kind not in kinds:
        return None, [f"{where}.{kind}: unknown distribution (one of {', '.join(kinds)})"]
    if (not isinstance(args, list) or len(args) != 2 or any(isinstance(a, bool) or not isinstance(a, (int, float))
                                                          or not math.isfinite(a) for a in args)):
        return None, [f"{where}.{kind}: must be two finite numbers, got {args!r}"]
    a, b = float(args[0]), float(args[1])
    if kind.endswith("normal"):
        if b < 0:
            return None, [f"{where}.{kind}: [mean, std]: std must be >= 0, got {b:g}"]
    elif not a <= b:
        return None, [f"{where}.{kind}: [lo, hi] needs lo <= hi, got {args!r}"]
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
            d, errs = _dist(v, f"{path}.{key}")
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
    errors = [f"{path}[{i}]: {m!r} unknown (one of {', '.join(METRICS)})" for i, m in enumerate(value)
              if m not in METRICS]
    if len(set(value)) != len(value):
        errors.append(f"{path}: lists a metric twice")
    return tuple(value), errors


def sweep_schema(base_dir: Path) -> dict[str, Any]:
    """What a sweep file may say (docs/sweeps.md)."""
    return {
        "version": Num(default=1, integer=True, min=1, max=1, doc="sweep format version (1)"),
        "name": Str(default=None, optional=True, doc="sweep name (figure titles)"),
        "description": Str(default=None, optional=True, doc="free text"),
        "base": Custom(_base_check(base_dir), doc="experiment file, or name → experiment file (an axis 'base')"),
        "grid": Custom(_grid_check, default=None,
                       doc="key path → list of values; or an axis name → {value name: {key path: value}}"),
        "random": Custom(_random_check, default=None,
                         doc="n draws (seed) of key path → distribution; with the grid as a product"),
        "metrics": Custom(_metrics_check, default=None, doc="figures kept per point"),
    }


def is_sweep_file(data: Any) -> bool:
    """A sweep file has ``base:`` where an experiment has ``version``/``safety``."""
    return isinstance(data, dict) and "base" in data


def load_sweep(path: str | Path) -> Sweep:
    """Load and validate a sweep file; ConfigError lists every problem with its key path."""
    p = Path(path)
    data = load_yaml(p)
    if not isinstance(data, dict):
        raise ConfigError([f"sweep: must be a mapping, got {type(data).__name__}"], str(p))
    node, errors = validate_fields(sweep_schema(p.parent), data, "")
    if errors:
        raise ConfigError(errors, str(p))
    rnd = node.random
    sweep = Sweep(source=str(p), name=node.name or p.stem, bases=node.base, grid=dict(node.grid),
                  random_n=rnd[0] if rnd else None, random_seed=rnd[1] if rnd else 0,
                  random=rnd[2] if rnd else {}, metrics=node.metrics)
    sweep.raw_bases = {k: load_yaml(f) for k, f in sweep.bases.items()}
    clash = [a for a in sweep.random if a in sweep.grid]
    if clash:
        raise ConfigError([f"random.{a}: also a grid axis; vary a key one way" for a in clash], str(p))
    if sweep.size() > MAX_POINTS:
        raise ConfigError([f"grid × random: {sweep.size()} points, more than {MAX_POINTS}"], str(p))
    return sweep


# --------------------------------------------------------------------------
# Applying values by key path
def _get(d: dict[str, Any], key: str) -> Any:
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


def _resolve_param_sets(data: dict[str, Any], base_dir: Path, needed: set[str]) -> None:
    """Parameter sets as plain numbers (Table I, a file, a file with overrides → a mapping)."""
    for key in ("parameters", "plant.parameters"):
        raw = _get(data, key)
        if raw is None and key == "plant.parameters":
            if not any(n.startswith("plant.parameters.") for n in needed):
                continue
            raw = copy.deepcopy(data.get("parameters", "table1"))  # the simulated damper runs the law's set
        kind, _f = params_input_kind(raw, base_dir)
        if kind != "current":
            if isinstance(raw, str) and not Path(raw).is_absolute():
                _set(data, key, str(base_dir / raw))
            continue  # a voltage set keeps its file (the file says what it takes)
        params, errors = params_check(base_dir)(raw, key)
        if errors:
            raise ConfigError(errors)
        _set(data, key, params.as_dict())
    bw = _get(data, "plant.model.parameters")
    if isinstance(bw, str):
        full = Path(bw) if Path(bw).is_absolute() else base_dir / bw
        _set(data, "plant.model.parameters", load_bouc_wen_file(full).as_dict())


def _draw(kind: str, a: float, b: float, rng: np.random.Generator) -> float:
    base = kind.removeprefix("factor_")
    if base == "uniform":
        return float(rng.uniform(a, b))
    if base == "normal":
        return float(rng.normal(a, b))
    return float(math.exp(rng.uniform(math.log(a), math.log(b))))


def _draws(sweep: Sweep, i: int) -> dict[str, tuple[str, float]]:
    """Draw ``i``'s values: the same for every grid cell (common random numbers)."""
    rng = np.random.default_rng([sweep.random_seed, i])
    return {key: (kind, _draw(kind, a, b, rng)) for key, (kind, a, b) in sweep.random.items()}


def _grid_cells(sweep: Sweep) -> Iterator[tuple[str, dict[str, Any], list[tuple[str, Any]]]]:
    """(base name, column values, overrides) per grid cell, in file order."""
    axes: list[list[tuple[Any, list[tuple[str, Any]]]]] = []
    for key, values in sweep.grid.items():
        if isinstance(values, list):
            axes.append([(v, [(key, v)]) for v in values])
        else:
            axes.append([(name, list((o or {}).items())) for name, o in values.items()])
    for base in sweep.bases:
        for combo in itertools.product(*axes):
            cols = {"base": base} if len(sweep.bases) > 1 else {}
            overrides: list[tuple[str, Any]] = []
            for key, (label, ov) in zip(sweep.grid, combo):
                cols[key] = label
                overrides += ov
            yield base, cols, overrides


def config_hash(config: dict[str, Any], base_dir: str, metrics: tuple[str, ...]) -> str:
    """The point's key for resumption: what runs and what is kept."""
    text = json.dumps({"config": config, "base_dir": base_dir, "metrics": list(metrics)}, sort_keys=True,
                      separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def resolve(sweep: Sweep, base: str, overrides: list[tuple[str, Any]],
            draws: dict[str, tuple[str, float]]) -> dict[str, Any]:
    """The point's experiment as plain data: base, then overrides (discriminators first), parameter
    sets read, then values inside parameter sets and the random draws."""
    base_dir = sweep.bases[base].parent
    sweep_dir = Path(sweep.source).parent
    data = copy.deepcopy(sweep.raw_bases[base])
    outer = [(k, v) for k, v in overrides if not _in_param_set(k)]
    inner = [(k, v) for k, v in overrides if _in_param_set(k)]
    for key, value in sorted(outer, key=lambda kv: kv[0].split(".")[-1] not in DISCRIMINATORS):
        _set(data, key, _absolute(key, value, sweep_dir))
    _resolve_param_sets(data, base_dir, {k for k, _ in overrides} | set(draws))
    for key, value in inner:
        _set(data, key, value)
    for key, (kind, x) in draws.items():
        if kind.startswith("factor_"):
            old = _get(data, key)
            if isinstance(old, bool) or not isinstance(old, (int, float)):
                raise ConfigError([f"random.{key}: a factor needs a number there, the point has {old!r}"])
            x = old * x
        _set(data, key, x)
    return data


def expand(sweep: Sweep) -> Iterator[Point | tuple[int, dict[str, Any], str]]:
    """Every point in order: the grid cells × the draws. A point whose values cannot even be applied
    (a factor on a missing key) comes as (index, values, error) and becomes a failed row."""
    index = 0
    n = sweep.random_n or 1
    for base, cols, overrides in _grid_cells(sweep):
        for i in range(n):
            draws = _draws(sweep, i) if sweep.random else {}
            values = {**cols, **{k: x for k, (_kind, x) in draws.items()}}
            base_dir = str(sweep.bases[base].parent)
            try:
                config = resolve(sweep, base, overrides, draws)
            except ConfigError as exc:
                yield index, values, "; ".join(exc.errors)
            else:
                values.update({k: _get(config, k) for k in draws})  # a factor's column: the value it gave
                p = Point(index, values, i if sweep.random else None, config, base_dir)
                p.hash = config_hash(config, base_dir, sweep.metrics)
                yield p
            index += 1


def sweep_markdown() -> str:
    """The sweep file's keys, its distributions and its metrics as markdown (docs/sweeps.md)."""
    from mrctl.sweep.metrics import METRIC_DOCS
    from mrctl.util.schema import schema_markdown

    dists = ", ".join(f"`{d}`" for d in DISTRIBUTIONS + tuple(f"factor_{d}" for d in DISTRIBUTIONS))
    return (schema_markdown(sweep_schema(Path("."))) + "\n\nDistributions of `random:`: " + dists
            + " (`uniform`/`log_uniform`: [lo, hi]; `normal`: [mean, std]; `factor_…`: the point's value times "
              "the draw).\n\n| metric | meaning |\n|---|---|\n"
            + "\n".join(f"| `{m}` | {d} |" for m, d in METRIC_DOCS.items()))

"""Parameter sets in a config: Table I, a parameters YAML, or inline overrides.

A parameters file holds the spec's names (docs/identification.md writes
them); inline overrides in an experiment change single values of a base set.

A file may say what its laws are a function of: ``input: current`` (A, the
default and Table I's) or ``input: voltage`` (V, a driver's command voltage:
a set identified from a voltage-driven bench), and ``input_range: [lo, hi]``,
the input range it was identified over. ``laws: table`` with a ``table:``
mapping (input levels, strictly increasing, and Θ at each) replaces the
paper's laws (6)–(11) by piecewise-linear interpolation of Θ
(:class:`mrctl.model.params.ThetaTable`; docs/identification.md). An experiment's ``backend.input``
must match (:func:`input_kind_errors`): a daemon that commands currents must
not run laws written in volts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

from mrctl.model.mapping import params_from_mapping, table_from_mapping
from mrctl.model.params import TABLE_BENCH_NAMES, TABLE_HYS_NAMES, TABLE_NAMES, LuGreParams
from mrctl.util.files import Fence
from mrctl.util.schema import ConfigError, key_repr, load_yaml, read_named_yaml, short_repr

__all__ = ["INPUT_KINDS", "ParamsFile", "read_params_file", "load_params_file", "params_check",
           "params_input_kind", "input_kind_errors"]

#: what a set's laws take, and the unit of that input
INPUT_KINDS: dict[str, str] = {"current": "A", "voltage": "V"}

_PARAM_FILE_META = ("version", "description", "source", "fit", "input", "input_range")


@dataclass(frozen=True)
class ParamsFile:
    """A parameters file: the set and what its laws take."""

    params: LuGreParams
    input: str = "current"  # a key of INPUT_KINDS
    input_range: tuple[float, float] | None = None  # identified over this input range (unit of ``input``)

    @property
    def unit(self) -> str:
        return INPUT_KINDS[self.input]


def _check_meta(data: dict[str, Any]) -> tuple[str, tuple[float, float] | None, list[str]]:
    errors: list[str] = []
    kind = data.get("input", "current")
    if kind not in INPUT_KINDS:
        errors.append(f"input: {short_repr(kind)} not allowed (allowed: {', '.join(INPUT_KINDS)}: what the laws take, "
                      "a coil current in A or a driver command voltage in V)")
        kind = "current"
    rng = data.get("input_range")
    out: tuple[float, float] | None = None
    if rng is not None:
        ok = (isinstance(rng, list) and len(rng) == 2
              and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(float(x)) for x in rng))
        if not ok or not float(rng[0]) < float(rng[1]):
            errors.append(f"input_range: must be [lo, hi] with lo < hi (the identified input range), got {short_repr(rng)}")
        else:
            out = (float(rng[0]), float(rng[1]))
    return kind, out, errors


def _set_errors(values: dict[Any, Any], path: str = "") -> list[str]:
    """A set's keys and values as the model takes them (spec names, finite
    numbers, ``laws``, a ``table`` of lists of numbers), each error naming
    its key as :func:`key_repr` allows and its value as :func:`short_repr`
    does: the model's own messages would quote them."""
    pre = f"{path}." if path else ""
    errors: list[str] = []
    names = LuGreParams.all_names()
    for k, v in values.items():
        if k == "laws":
            if v not in ("paper", "table", None):
                errors.append(f"{pre}laws: {short_repr(v)} not allowed (paper: laws (6)-(11); table: "
                              "interpolated per-level values)")
        elif k == "table":
            if isinstance(v, dict):
                allowed = ("input",) + TABLE_NAMES + TABLE_BENCH_NAMES + TABLE_HYS_NAMES
                errors += [f"{pre}table.{key_repr(t)}: unknown (expected {', '.join(allowed)})" for t in v
                           if t not in allowed]
        elif k not in names:
            errors.append(f"{pre}{key_repr(k)}: unknown parameter (expected: {', '.join(names)}, laws, table)")
        elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            errors.append(f"{pre}{k}: must be a finite number, got {short_repr(v)}")
    return errors


def read_params_file(path: str | Path) -> ParamsFile:
    """Read a parameters YAML: the spec's names, plus metadata keys
    (version, description, source, fit are ignored; ``input`` and
    ``input_range`` are checked and returned). A set whose laws leave the
    physical range (σ0, Fs, vs, Fc > 0) over its ``input_range`` is refused."""
    return params_from_data(load_yaml(path), str(path))


def params_from_data(data: Any, source: str | None = None) -> ParamsFile:
    """The parameters file's set from its parsed YAML (:func:`read_params_file`)."""
    if not isinstance(data, dict):
        raise ConfigError(["must be a mapping of parameter names to numbers"], source)
    values = {k: v for k, v in data.items() if k not in _PARAM_FILE_META}
    kind, rng, errors = _check_meta(data)
    errors += _set_errors(values)
    if errors:
        raise ConfigError(errors, source)
    try:
        params = params_from_mapping(values)
    except ValueError as exc:
        raise ConfigError(str(exc).split("; "), source) from None
    if rng is not None:
        problems = params.check_range(rng[1], I_min=rng[0], unit=INPUT_KINDS[kind])
        if problems:
            raise ConfigError([f"input_range: {p}" for p in problems], source)
    return ParamsFile(params, kind, rng)


def load_params_file(path: str | Path) -> LuGreParams:
    """The parameter set of a parameters YAML (see :func:`read_params_file`)."""
    return read_params_file(path).params


def _file_of(value: Any, base_dir: Path) -> Path | None:
    if isinstance(value, dict):
        value = value.get("file")
    if not isinstance(value, str) or value == "table1":
        return None
    return (base_dir / value) if not Path(value).is_absolute() else Path(value)


def params_input_kind(value: Any, base_dir: Path, fence: Fence | None = None) -> tuple[str, Path | None]:
    """What the set named by a raw ``parameters`` value takes, and its file.

    Table I and inline sets take a current; a file says (``input:``, default
    current). A file that cannot be read, or that ``fence`` does not admit,
    counts as current here (the parameters check reports why)."""
    f = _file_of(value, base_dir)
    if f is None:
        return "current", None
    fence = fence if fence is not None else Fence.around(base_dir)
    if fence.admit(str(f), base_dir, "parameters")[0] is None:
        return "current", f
    try:
        data = load_yaml(f)
    except ConfigError:
        return "current", f
    kind = data.get("input", "current") if isinstance(data, dict) else "current"
    return (kind if kind in INPUT_KINDS else "current"), f


def input_kind_errors(data: Any, base_dir: Path, backend_input: Any, fence: Fence | None = None) -> list[str]:
    """``parameters`` and ``plant.parameters`` against ``backend.input``: the
    laws must take what the driver takes. One line per mismatch, naming both keys."""
    if not isinstance(data, dict) or backend_input not in INPUT_KINDS:
        return []
    errors = []
    plant = data.get("plant")
    for key, raw in (("parameters", data.get("parameters")),
                     ("plant.parameters", plant.get("parameters") if isinstance(plant, dict) else None)):
        if raw is None and key == "plant.parameters":
            continue  # the simulated damper runs the law's set, checked above
        kind, f = params_input_kind(raw, base_dir, fence)
        if kind != backend_input:
            errors.append(
                f"{key}: the set in {f or 'table1'} takes a {kind} ({INPUT_KINDS[kind]}: input: {kind}), but backend.input "
                f"is '{backend_input}' ({INPUT_KINDS[backend_input]}): use a set identified for a {backend_input} "
                f"input, or set backend.input: {kind} if the driver really takes a {kind}")
    return errors


def params_check(base_dir: Path, fence: Fence | None = None) -> Callable[[Any, str], tuple[Any, list[str]]]:
    """A ``parameters`` value: 'table1', a file (admitted by ``fence``,
    default under ``base_dir``'s folder; read without quoting it), or
    ``{file: ..., <name>: value}`` overrides."""
    fence = fence if fence is not None else Fence.around(base_dir)

    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if value is None and path.endswith("plant.parameters"):
            return None, []  # the simulated damper uses the law's set
        if value is None or value == "table1":
            return LuGreParams(), []
        if isinstance(value, str):
            value = {"file": value}
        if not isinstance(value, dict):
            return None, [f"{path}: must be 'table1', a parameters file path, or a mapping of parameter names"]
        overrides = dict(value)
        base = LuGreParams()
        if "file" in overrides:
            pf, errs = read_named_yaml(overrides.pop("file"), base_dir, fence, f"{path}.file",
                                       lambda full, data: params_from_data(data))
            if pf is None:
                return None, errs
            base = pf.params
        errors = _set_errors(overrides, path)
        if errors:
            return None, errors
        if "laws" in overrides or "table" in overrides:  # laws: table inline (a sweep writes sets so)
            try:
                base = replace(base, table=table_from_mapping(overrides.pop("laws", "paper"),
                                                              overrides.pop("table", None)))
            except ValueError as exc:
                return None, [f"{path}.{e}" for e in str(exc).split("; ")]
        return base.with_overrides(**{k: float(v) for k, v in overrides.items()}), []

    return check

"""Parameter sets in a config: Table I, a parameters YAML, or inline overrides.

A parameters file holds the spec's names (docs/identification.md writes
them); inline overrides in an experiment change single values of a base set.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

from mrctl.model.params import LuGreParams, params_from_mapping
from mrctl.util.schema import ConfigError, load_yaml

_PARAM_FILE_META = ("version", "description", "source", "fit")


def load_params_file(path: str | Path) -> LuGreParams:
    """Read a parameters YAML (keys: the spec's names, plus metadata keys
    version/description/source/fit which are ignored)."""
    data = load_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(["must be a mapping of parameter names to numbers"], str(path))
    values = {k: v for k, v in data.items() if k not in _PARAM_FILE_META}
    errors = []
    known = set(LuGreParams.all_names())
    for k in values:
        if k not in known:
            errors.append(f"{k}: unknown parameter (expected: {', '.join(LuGreParams.all_names())})")
    if errors:
        raise ConfigError(errors, str(path))
    try:
        return params_from_mapping(values)
    except ValueError as exc:
        raise ConfigError([str(exc)], str(path)) from None


def params_check(base_dir: Path) -> Callable[[Any, str], tuple[Any, list[str]]]:
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
            fpath = overrides.pop("file")
            if not isinstance(fpath, str):
                return None, [f"{path}.file: must be a path string, got {fpath!r}"]
            full = (base_dir / fpath) if not Path(fpath).is_absolute() else Path(fpath)
            try:
                base = load_params_file(full)
            except ConfigError as exc:
                return None, [f"{path}.file ({full}): {e}" for e in exc.errors]
        errors = []
        good: dict[str, float] = {}
        known = set(LuGreParams.all_names())
        for k, v in overrides.items():
            if k not in known:
                errors.append(f"{path}.{k}: unknown parameter (expected: file, {', '.join(LuGreParams.all_names())})")
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                errors.append(f"{path}.{k}: must be a finite number, got {v!r}")
            else:
                good[k] = float(v)
        if errors:
            return None, errors
        return base.with_overrides(**good), []

    return check

"""The simulated damper's model in a config: ``plant.model``.

``plant.model.type`` names the model the simulated bench runs (the plant
name table, :data:`PLANT_MODELS`; :mod:`mrctl.experiment` builds them):

- ``lugre`` (default): the forward LuGre model with ``plant.parameters``
  (or the law's own set);
- ``bouc-wen``: Spencer et al.'s phenomenological model with its own
  first-order coil filter, its constants from a YAML file
  (``config/plants/rd1097_bouc_wen.yaml`` is fitted to Table I's damper by
  ``bench/fit_bouc_wen.py``; docs/robust-tracking.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from mrctl.model.boucwen import BoucWenParams, bw_params_from_mapping
from mrctl.util.schema import ConfigError, Custom, Num, Union, load_yaml, short_repr

#: metadata keys a plant parameters file may carry besides the constants
_META = ("version", "description", "source", "fit")

#: plant.model.type names (the builders are in mrctl.experiment.PLANTS)
PLANT_MODELS = ("lugre", "bouc-wen")


def load_bouc_wen_file(path: str | Path) -> BoucWenParams:
    """Read a Bouc–Wen parameters YAML (the names of :class:`BoucWenParams`)."""
    data = load_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError([f"must be a mapping of {', '.join(BoucWenParams.names())}"], str(path))
    try:
        return bw_params_from_mapping({k: v for k, v in data.items() if k not in _META})
    except ValueError as exc:
        raise ConfigError([str(exc)], str(path)) from None


def _bw_file_check(base_dir: Path) -> Callable[[Any, str], tuple[Any, list[str]]]:
    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if isinstance(value, dict):  # inline constants (a sweep ships its points as plain data)
            try:
                return bw_params_from_mapping(value), []
            except ValueError as exc:
                return None, [f"{path}.{exc}" if ":" in str(exc) else f"{path}: {exc}"]
        if not isinstance(value, str) or not value:
            return None, [f"{path}: must be a Bouc–Wen parameters file path or a mapping of its constants, "
                          f"got {short_repr(value)}"]
        full = Path(value) if Path(value).is_absolute() else base_dir / value
        if not full.is_file():
            return None, [f"{path}: no such file: {full}"]
        try:
            return load_bouc_wen_file(full), []
        except ConfigError as exc:
            return None, [f"{path} ({full}): {e}" for e in exc.errors]

    return check


def plant_model_schema(base_dir: Path) -> Union:
    """``plant.model``: which damper model the simulated bench runs."""
    return Union("type", {
        "lugre": {},
        "bouc-wen": {
            "parameters": Custom(_bw_file_check(base_dir),
                                 doc="Bouc–Wen parameters YAML (e.g. config/plants/rd1097_bouc_wen.yaml), or its constants inline"),
            "substeps": Num(default=8, integer=True, min=1, max=64,
                            doc="integration substeps per tick (the Bouc–Wen state is stiff)"),
        },
    }, default="lugre", doc="damper model of the simulated bench: lugre (plant.parameters) or bouc-wen "
                            "(Spencer et al. 1997, its own coil filter; plant.driver_tau_s overrides it)")

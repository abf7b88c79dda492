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

from mrctl.model.boucwen import BoucWenParams, bw_errors, bw_params_from_mapping
from mrctl.util.files import Fence
from mrctl.util.schema import ConfigError, Custom, Num, Union, load_yaml, read_named_yaml, short_repr

#: metadata keys a plant parameters file may carry besides the constants
_META = ("version", "description", "source", "fit")

#: plant.model.type names (the builders are in mrctl.experiment.PLANTS)
PLANT_MODELS = ("lugre", "bouc-wen")


def load_bouc_wen_file(path: str | Path) -> BoucWenParams:
    """Read a Bouc–Wen parameters YAML (the names of :class:`BoucWenParams`)."""
    return bouc_wen_from_data(load_yaml(path), str(path))


def bouc_wen_from_data(data: Any, source: str | None = None, file: bool = True) -> BoucWenParams:
    """The constants of a parsed Bouc–Wen file (its metadata keys aside) or
    of an inline mapping (``file`` False); every key and value checked by
    :func:`mrctl.model.boucwen.bw_errors`, all errors at once."""
    if not isinstance(data, dict):
        raise ConfigError([f"must be a mapping of {', '.join(BoucWenParams.names())}"], source)
    values = {k: v for k, v in data.items() if not (file and k in _META)}
    errors = bw_errors(values)
    if errors:
        raise ConfigError(errors, source)
    return bw_params_from_mapping(values)


def _bw_file_check(base_dir: Path, fence: Fence | None) -> Callable[[Any, str], tuple[Any, list[str]]]:
    fence = fence if fence is not None else Fence.around(base_dir)

    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if isinstance(value, dict):  # inline constants (a sweep ships its points as plain data)
            try:
                return bouc_wen_from_data(value, file=False), []
            except ConfigError as exc:
                return None, [f"{path}.{e}" if ":" in e else f"{path}: {e}" for e in exc.errors]
        if not isinstance(value, str) or not value:
            return None, [f"{path}: must be a Bouc–Wen parameters file path or a mapping of its constants, "
                          f"got {short_repr(value)}"]
        return read_named_yaml(value, base_dir, fence, path, lambda full, data: bouc_wen_from_data(data))

    return check


def plant_model_schema(base_dir: Path, fence: Fence | None = None) -> Union:
    """``plant.model``: which damper model the simulated bench runs."""
    return Union("type", {
        "lugre": {},
        "bouc-wen": {
            "parameters": Custom(_bw_file_check(base_dir, fence),
                                 doc="Bouc–Wen parameters YAML (e.g. config/plants/rd1097_bouc_wen.yaml), or its constants inline"),
            "substeps": Num(default=8, integer=True, min=1, max=64,
                            doc="integration substeps per tick (the Bouc–Wen state is stiff)"),
        },
    }, default="lugre", doc="damper model of the simulated bench: lugre (plant.parameters) or bouc-wen "
                            "(Spencer et al. 1997, its own coil filter; plant.driver_tau_s overrides it)")

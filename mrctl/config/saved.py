"""The experiment as a run log's sidecar keeps it: JSON that validates back.

Validation turns some keys into live values (``backend.register_map`` into a
``RegisterMap``, ``backend.device`` into the preset with its wiring), so the
validated node written as it is does not validate when read back (a replay
of every Modbus or T7 run log exited 2). :func:`saved_config` writes each
such key in the form the schema takes (a register map as its mapping,
``jsonable``'s ``to_mapping``; a device as its preset's name beside the
channels the user wrote), so that
``validate_experiment(saved_config(cfg))`` is ``cfg`` again;
:func:`readable_config` mends the forms that older sidecars hold.
"""

from __future__ import annotations

import copy
from typing import Any

from mrctl.util.jsonutil import jsonable
from mrctl.util.schema import Node

__all__ = ["saved_config", "readable_config"]


def saved_config(cfg: Node) -> dict[str, Any]:
    """``cfg`` (a validated experiment) as plain JSON that validates back to it."""
    data: dict[str, Any] = jsonable(cfg)
    backend = data.get("backend")
    live = cfg.get("backend")
    if isinstance(backend, dict) and live is not None:
        device = live.get("device")
        if device is not None:  # the preset builds the map from the channels the user wrote
            backend["device"] = device.preset.name
            backend.pop("register_map", None)
    return data


def readable_config(data: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """A sidecar's ``config`` ready to validate, and what was mended: an
    older sidecar kept a device preset as its set-up (a mapping naming the
    preset) and a register map as its description (a string), neither of
    which validates. A replay runs on the in-process bench, which reads no
    register, so a described map is dropped (the default map) and said."""
    out = copy.deepcopy(data)
    notes: list[str] = []
    backend = out.get("backend")
    if isinstance(backend, dict):
        dev = backend.get("device")
        if isinstance(dev, dict) and isinstance(dev.get("device"), str):
            backend["device"] = dev["device"]
            backend.pop("register_map", None)
        elif isinstance(backend.get("register_map"), str):
            backend.pop("register_map")
            notes.append("the sidecar keeps only a description of backend.register_map (a sidecar of mrctl "
                         "before 2026-11-27); the replay uses the default map (an offline replay reads no register)")
    return out, notes

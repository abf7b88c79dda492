"""One way to turn run metadata into strict JSON (sidecars, status, summaries).

Config nodes, parameter sets, counters (dataclasses), numpy scalars and
arrays, sets and tuples all appear in what we write; strict JSON has no
NaN/inf, so non-finite floats become ``"nan"``/``"inf"``/``"-inf"`` strings
(sidecars: readable, round-trippable by eye) or ``null`` (the status
socket, for clients that want numbers or nothing).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Mapping
from typing import Any

import numpy as np


def jsonable(obj: Any, nonfinite: str = "repr") -> Any:
    """A strict-JSON-serializable copy of ``obj``; ``nonfinite``: "repr" or "null"."""
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        if math.isfinite(f):
            return f
        return repr(f) if nonfinite == "repr" else None
    if obj is None or isinstance(obj, (str, bool, int)):
        return obj
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), nonfinite)
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v, nonfinite) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset, deque)):
        return [jsonable(v, nonfinite) for v in obj]
    for method in ("to_dict", "as_dict", "to_mapping"):  # config Node, LuGreParams, SafetyCounters, RegisterMap
        if callable(getattr(obj, method, None)):
            return jsonable(getattr(obj, method)(), nonfinite)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return jsonable(dataclasses.asdict(obj), nonfinite)
    return str(obj)

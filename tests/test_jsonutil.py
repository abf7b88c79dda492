"""The one JSON normalizer: every type our metadata holds, both NaN policies."""

import json
import math

import numpy as np

from pathlib import Path

from mrctl.config import validate_experiment
from mrctl.util.jsonutil import jsonable
from mrctl.model.params import TABLE_I
from mrctl.core.safety import SafetyConfig, SafetySupervisor


def test_types_and_nonfinite_policies():
    data = {"a": (1, 2.5), "s": frozenset({3}), "n": np.float64(math.nan), "i": np.int32(7),
            "arr": np.array([1.0, math.inf]), "p": TABLE_I, 4: -math.inf,
            "c": SafetySupervisor(SafetyConfig(I_max=0.6)).counters()}
    out = jsonable(data)
    json.dumps(out, allow_nan=False)  # strict JSON
    assert out["a"] == [1, 2.5] and out["s"] == [3] and out["i"] == 7
    assert out["n"] == "nan" and out["arr"] == [1.0, "inf"] and out["4"] == "-inf"
    assert out["p"]["F0"] == 2.90 and out["c"]["good"] == 0
    assert jsonable(data, nonfinite="null")["n"] is None


def test_config_node_is_serialised():
    cfg = validate_experiment({"version": 1, "excitation": {"type": "sine", "amplitude_m": 0.01, "frequency_hz": 1},
                               "demand": {"type": "viscous", "c_des": 500}, "inverse": {"law": "paper"},
                               "safety": {"I_max": 0.6, "v_range_mps": [-1, 1]}, "rt": {"cpus": [0]}}, Path("."))
    out = jsonable(cfg)
    json.dumps(out, allow_nan=False)
    assert out["rt"]["cpus"] == [0] and out["safety"]["v_range_mps"] == [-1.0, 1.0]
    assert out["parameters"]["Bc"] == -0.176

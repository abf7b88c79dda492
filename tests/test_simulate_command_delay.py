"""mrctl simulate models an exchange link's actuation delay (plant.command_delay_ticks, issue 34):
the current computed from tick k's sample reaches the bench at tick k + d."""

import copy
from pathlib import Path

import numpy as np
import pytest

from mrctl.config import ConfigError, load_yaml, validate_experiment
from mrctl.experiment import build
from mrctl.offline.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
EXP = ROOT / "config" / "experiments"


def _exp(name: str, **plant):
    data = copy.deepcopy(load_yaml(EXP / name))
    data.setdefault("plant", {}).update(plant)
    return build(validate_experiment(data, EXP))


@pytest.mark.parametrize("delay", [0, 1, 3])
def test_each_current_reaches_the_bench_delay_ticks_after_its_sample(delay):
    """No driver lag: the applied current of tick k is the law's current of tick k - d (0 A before)."""
    res = simulate(_exp("fig5.yaml", driver_tau_s=0.0, command_delay_ticks=delay), 0.3)
    I, applied = res.columns["I"], res.columns["I_applied"]
    assert np.any(I > 0.05)  # the law drives the damper: the comparison is not of zeros
    assert np.array_equal(applied[delay:], I[:len(I) - delay])
    assert np.all(applied[:delay] == 0.0)


def test_the_delay_is_carried_across_blocks():
    """A run cut into blocks is the same run, bit for bit, with a delay as without."""
    exp = _exp("fig5.yaml", command_delay_ticks=2)
    whole = simulate(exp, 0.3).columns
    exp = _exp("fig5.yaml", command_delay_ticks=2)
    cut = simulate(exp, 0.3, block_ticks=7).columns
    for c in ("I", "I_applied", "F", "F_des"):
        assert np.array_equal(whole[c], cut[c]), c


@pytest.mark.parametrize("name, ticks", [("labjack_t7.yaml", 1), ("hil_serial.yaml", 1), ("hil_modbus_tcp.yaml", 1),
                                         ("fig5.yaml", 0)])
def test_auto_is_one_tick_on_an_exchange_link_and_none_on_the_sim(name, ticks):
    assert _exp(name, command_delay_ticks="auto").command_delay_ticks == ticks


def test_the_default_is_no_delay():
    assert _exp("hil_serial.yaml").command_delay_ticks == 0


@pytest.mark.parametrize("value", [-1, 0.5, "sometimes", True])
def test_a_bad_delay_is_refused_with_its_key(value):
    with pytest.raises(ConfigError, match="plant.command_delay_ticks"):
        _exp("fig5.yaml", command_delay_ticks=value)


def test_the_t7_experiment_simulates_its_links_delay():
    """The shipped T7 experiment asks for 'auto': one tick, as its MBFB link sends each current."""
    exp = build(validate_experiment(load_yaml(EXP / "labjack_t7.yaml"), EXP))
    assert exp.config.plant.command_delay_ticks == "auto" and exp.command_delay_ticks == 1

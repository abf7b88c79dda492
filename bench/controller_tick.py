"""The real controller tick for bench/loop_timing.py: fig5 on the in-process sim
bench, with the safety supervisor and the recorder (writing to a temp file),
exactly as ``mrctl run`` builds it.

    python bench/loop_timing.py --tick controller_tick:make_tick
    python bench/loop_timing.py --tick controller_tick:make_plugin_tick    # the example plugin's laws
    python bench/loop_timing.py --tick controller_tick:make_skyhook_tick   # skyhook on the quarter car
    python bench/loop_timing.py --tick controller_tick:make_tick_robust   # closed law + velocity observer
    python bench/loop_timing.py --tick controller_tick:make_tick_robust_replay   # the same, plant excluded

The ``_replay`` ticks run the controller on a link that replays the samples
``mrctl simulate`` recorded for the same file, one exchange per tick as the
serial and Modbus links do: the controller's compute (safety, observer,
laws, record) without the in-process plant, which on a real bench is the
DAQ's and the damper's, not the host's.

``make_plugin_tick`` runs the example plugin (examples/mrctl-law-example:
``sine_force`` demand, ``force_pi`` inverse law) named as module:Class,
the same classes its entry points name, on fig5's shaker.
"""

from __future__ import annotations

import atexit
import math
import sys
import tempfile
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mrctl.config import load_experiment  # noqa: E402
from mrctl.core.controller import Controller  # noqa: E402
from mrctl.daemon.recorder import Recorder  # noqa: E402
from mrctl.core.safety import SafetyConfig, SafetySupervisor  # noqa: E402
from mrctl.experiment import Experiment, build  # noqa: E402
from mrctl.io.base import Link, Sample, Status  # noqa: E402
from mrctl.offline.simulate import log_columns, run_duration, simulate  # noqa: E402
from mrctl.runlog.format import RUN_COLUMNS, RUN_FORMATS  # noqa: E402

CONFIG = ROOT / "config" / "experiments" / "fig5.yaml"
#: the closed law with the velocity observer, on a displacement-only DAQ (LuGre bench, noisy LVDT and load cell)
ROBUST = ROOT / "config" / "experiments" / "robust" / "displacement_only_c500.yaml"
PLUGIN_SRC = ROOT / "examples" / "mrctl-law-example" / "src"


def make_tick(period_s: float, defer_format: bool = True, config: Path = CONFIG
              ) -> tuple[Callable[[int, int], object], Callable[[int], object] | None]:
    """(tick, background): as ``mrctl run`` builds them; with ``defer_format``
    the loop formats the log in its idle time (the background hook)."""
    exp = build(load_experiment(config))
    backend = exp.make_link()
    backend.open()
    return _controller(exp, backend, defer_format)


def _controller(exp: Experiment, link: Link, defer_format: bool = True
                ) -> tuple[Callable[[int, int], object], Callable[[int], object] | None]:
    """The controller on ``link`` with the supervisor and the recorder (a temp
    file), as ``mrctl run`` builds them; (tick, background)."""
    sys.setswitchinterval(2e-4)  # as mrctl run does: the writer thread must not hold the GIL for 5 ms
    sup = SafetySupervisor(SafetyConfig.from_config(exp.config.safety, exp.dt))
    tmp = tempfile.mkdtemp(prefix="mrctl-bench-")
    rec = Recorder(Path(tmp) / "run.csv", RUN_COLUMNS, {"bench": "loop_timing"}, capacity_ticks=65536,
                   fmt=RUN_FORMATS, defer_format=defer_format)
    ctl = Controller(link, exp.law, exp.demand, sup, exp.dt, record=rec.record, lead=exp.make_lead(link),
                     observer=exp.make_observer())
    atexit.register(rec.close)
    return ctl.tick, (rec.format_pending if defer_format else None)


def make_tick_thread_format(period_s: float) -> tuple[Callable[[int, int], object], None]:
    """The same, with the log formatted by the writer thread (the old design),
    for comparison: ``--tick controller_tick:make_tick_thread_format``."""
    return make_tick(period_s, defer_format=False)  # type: ignore[return-value]


def _edited(text: str) -> Path:
    p = Path(tempfile.mkdtemp(prefix="mrctl-bench-")) / "exp.yaml"
    p.write_text(text)
    return p


def make_plugin_tick(period_s: float) -> tuple[Callable[[int, int], object], Callable[[int], object] | None]:
    """fig5 with the example plugin's two laws in the 1 kHz path."""
    sys.path.insert(0, str(PLUGIN_SRC))
    text = CONFIG.read_text().replace("demand: {type: viscous, c_des: 500.0}",
                                      "demand: {type: 'mrctl_law_example.laws:SineForce', amplitude_N: 30.0, "
                                      "frequency_hz: 1.0, phase_rad: 1.5708}")
    head, _, tail = text.partition("inverse:\n")
    tail = tail.split("safety:", 1)[1]
    text = head + "inverse: {law: 'mrctl_law_example.laws:ForcePI'}\nsafety:" + tail
    return make_tick(period_s, config=_edited(text))


def make_skyhook_tick(period_s: float) -> tuple[Callable[[int, int], object], Callable[[int], object] | None]:
    """Skyhook + smooth on the quarter car (config/experiments/quarter_car.yaml)."""
    return make_tick(period_s, config=ROOT / "config" / "experiments" / "quarter_car.yaml")


def make_tick_robust(period_s: float) -> tuple[Callable[[int, int], object], Callable[[int], object] | None]:
    """The closed law with the velocity observer (``sensing.velocity: observer``)
    on a displacement-only sim bench: ``--tick controller_tick:make_tick_robust``."""
    return make_tick(period_s, config=ROBUST)


class ReplayLink(Link):
    """An exchange-shaped link that returns recorded samples in turn (and
    wraps around): what the controller sees of a real DAQ, at the cost of a
    tuple per tick, with no plant behind it."""

    kinds = ("replay",)

    def __init__(self, samples: list[Sample], dt: float) -> None:
        super().__init__(timeout_s=1.0)
        self.samples, self.dt, self.i, self._open = samples, dt, 0, False

    @classmethod
    def from_config(cls, cfg, context=None) -> "ReplayLink":
        raise NotImplementedError("built by bench/controller_tick.py only")

    @property
    def is_open(self) -> bool:
        return self._open

    def _open_transport(self) -> None:
        self._open = True

    def _close_transport(self) -> None:
        self._open = False

    def describe(self) -> str:
        return f"replay of {len(self.samples)} recorded samples"

    def _transact(self, current_A: float, deadline: float, wake_ns: int) -> Sample:
        i = self.i
        s = self.samples[i % len(self.samples)]
        self.i = i + 1
        n = i // len(self.samples)  # keep seq and device time moving on every lap
        if n:
            s = Sample(s.seq + n * len(self.samples), s.t_dev_s + n * len(self.samples) * self.dt, *s[2:])
        return s

    @property
    def true_force_N(self) -> float:
        return math.nan


def make_replay_tick(period_s: float, config: Path = CONFIG
                     ) -> tuple[Callable[[int, int], object], Callable[[int], object] | None]:
    """(tick, background) as ``mrctl run`` builds them, on a :class:`ReplayLink`
    of ``mrctl simulate``'s samples for ``config``."""
    exp = build(load_experiment(config))
    c = log_columns(simulate(exp, run_duration(exp)))  # x, F, I_applied as the controller received them
    vs = c["v"].tolist() if exp.config.plant.sensors.velocity else [math.nan] * len(c["v"])  # no channel: NaN
    status = int(Status.OUTPUT_ENABLED)
    samples = [Sample(k, k * exp.dt, x, v, F, status, Ia)
               for k, (x, v, F, Ia) in enumerate(zip(c["x"].tolist(), vs, c["F"].tolist(), c["I_applied"].tolist()))]
    exp.law.reset()  # the laws start afresh; the controller makes its own observer
    if exp.demand is not None:
        exp.demand.reset()
    link = ReplayLink(samples, exp.dt)
    link.open()
    return _controller(exp, link)


def make_tick_replay(period_s: float) -> tuple[Callable[[int, int], object], Callable[[int], object] | None]:
    """fig5 (the smooth law) on a replay of its samples: the baseline of the next."""
    return make_replay_tick(period_s, CONFIG)


def make_tick_robust_replay(period_s: float) -> tuple[Callable[[int, int], object], Callable[[int], object] | None]:
    """The closed law with the velocity observer, displacement-only samples replayed."""
    return make_replay_tick(period_s, ROBUST)

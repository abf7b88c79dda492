"""The progress bar every long command uses (mrctl/util/progress.py), on a
log or pipe: a line per tenth of the work, not before ``delay_s``, and every
``every_s`` between (virtual clock)."""

from __future__ import annotations

import io

import pytest

from mrctl.util import progress


@pytest.fixture
def clock(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: now[0])
    return now


def test_a_line_per_tenth_with_the_counts(clock):
    out = io.StringIO()
    bar = progress.make_bar(1000, "simulate", stream=out, unit="ticks")
    for _ in range(10):
        clock[0] += 1.0
        bar.update(100)
    lines = out.getvalue().splitlines()
    assert len(lines) == 10
    assert lines[0] == "simulate:  10% 100/1000 ticks (1.0 s)" and lines[-1].startswith("simulate: 100% 1000/1000")


def test_nothing_before_the_delay_then_the_next_tenth(clock):
    out = io.StringIO()
    bar = progress.make_bar(100, "simulate", stream=out, delay_s=2.0)
    for _ in range(5):  # half the work in 1 s: quick, so silent
        clock[0] += 0.2
        bar.update(10)
    assert out.getvalue() == ""
    clock[0] += 1.5
    bar.update(10)  # 60 % after 2.5 s
    assert out.getvalue().splitlines() == ["simulate:  60% (2.5 s)"]


def test_every_s_between_tenths_and_a_resumed_start(clock):
    out = io.StringIO()
    bar = progress.make_bar(1000, "sweep", stream=out, initial=500, unit="pt", every_s=5.0)
    for _ in range(3):  # 1 point every 3 s: no new tenth, a line every 5 s at most
        clock[0] += 3.0
        bar.update()
    assert [ln.split(" (")[0] for ln in out.getvalue().splitlines()] == ["sweep:  50% 501/1000 pt",
                                                                         "sweep:  50% 503/1000 pt"]


def test_disabled_prints_nothing(clock):
    out = io.StringIO()
    bar = progress.make_bar(10, "identify", enabled=False, stream=out)
    bar.update(10)
    bar.close()
    assert out.getvalue() == ""

"""``mrctl check SWEEP.yaml``: the sweep file's schema, then every point's config."""

from __future__ import annotations

from collections import Counter

from mrctl.config import ConfigError, validate_experiment
from mrctl.sweep.spec import load_sweep, expand
from pathlib import Path

#: points listed by their error at most
SHOWN = 5


def check_sweep(path: str) -> int:
    """0 when the file is valid (points that will fail are listed, not an error: they become failed rows);
    the sweep file's own errors raise ConfigError (exit 2)."""
    sweep = load_sweep(path)
    bad: Counter[str] = Counter()
    first: dict[str, int] = {}
    n = 0
    for p in expand(sweep):
        n += 1
        if isinstance(p, tuple):
            err, idx = p[2], p[0]
        else:
            try:
                validate_experiment(p.config, Path(p.base_dir))
                continue
            except ConfigError as exc:
                err, idx = "; ".join(exc.errors), p.index
        bad[err] += 1
        first.setdefault(err, idx)
    print(f"{path}: {n} points ({', '.join(sweep.axes) or 'no axes'}; metrics {', '.join(sweep.metrics)})")
    for err, count in bad.most_common(SHOWN):
        print(f"{path}: warning: {count} point(s) will fail (first: point {first[err]}): {err}")
    print(f"{path}: OK" + (f" ({sum(bad.values())} points invalid: rows with their error)" if bad else ""))
    return 0

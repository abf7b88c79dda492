"""The law sections of an experiment: ``demand`` and ``inverse``.

Their choices come from :mod:`mrctl.laws.registry`: the built-ins are the
schema's listed variants (so ``docs/config.md`` shows them), and any other
name (an installed entry point, or ``package.module:Class``) is resolved
when a file names it, its class's ``params`` then validated with key paths
exactly like a built-in's. ``mrctl check`` prints what is installed
(:func:`laws_report`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping

from mrctl.config.bench import BENCH_CHANNELS, quarter_car_params
from mrctl.laws.base import LawContext
from mrctl.laws.registry import BUILTIN, all_laws, find_law
from mrctl.model.params import LuGreParams
from mrctl.util.files import Fence
from mrctl.util.schema import Node, Num, Section, Union, bind_paths, schema_markdown

SECTIONS = (("demand", "demand", "type"), ("inverse", "current", "law"))  # (section, kind, key)

#: ``safety`` keys of the law guard (docs/laws.md)
LAW_GUARD_FIELDS = {
    "law_budget_s": Num(default=None, optional=True, min=0.0, min_exclusive=True, max=1.0,
                        doc="a tick whose law calls take longer is slow; null = one tick period"),
    "law_overrun_ticks": Num(default=3, integer=True, min=1, max=100000,
                             doc="this many slow ticks in a row are a law fault: 0 A, the run ends (exit 1)"),
}


def _resolver(kind: str, base_dir: Path, fence: Fence | None
              ) -> Callable[[str], tuple[Mapping[str, Any] | None, str | None]]:
    def resolve(name: str) -> tuple[Mapping[str, Any] | None, str | None]:
        info = find_law(kind, name)
        if info.cls is None:
            return None, info.error
        return bind_paths(info.cls.params, base_dir, fence), None

    return resolve


def law_unions(base_dir: Path, fence: Fence | None = None) -> dict[str, Union]:
    """The ``demand`` and ``inverse`` unions; file paths admitted by ``fence``
    (default: under ``base_dir``'s folder)."""
    def variants(kind: str) -> dict[str, Any]:
        return {name: bind_paths(cls.params, base_dir, fence) for name, cls in BUILTIN[kind].items()}

    return {
        "demand": Union("type", variants("demand"), optional=True, resolve=_resolver("demand", base_dir, fence),
                        doc="desired-force law (built-ins below; an installed plugin's name or "
                            "package.module:Class: docs/laws.md). Needed when the current law needs a demand"),
        "inverse": Union("law", variants("current"), resolve=_resolver("current", base_dir, fence),
                         doc="current law: an inverse law for demand's force, or a law that decides the "
                             "current (built-ins below; plugins: docs/laws.md)"),
    }


def law_context(cfg: Node, base_dir: Path = Path(".")) -> LawContext:
    """What laws are built with: the model, the limits, the tick, and what the
    plant section says about the bench (its channels on the sim link, the
    quarter car for laws that need the vehicle)."""
    plant = cfg.get("plant")
    qc = quarter_car_params(plant)
    backend = cfg.get("backend")
    channels = BENCH_CHANNELS.get(plant.get("bench", "shaker"), ()) if plant is not None else ()
    if backend is not None and backend.get("type") != "sim":
        channels = ()  # a real link says what it has when it is opened
    return LawContext(cfg.parameters, cfg.safety.I_max, 1.0 / cfg.rate_hz, base_dir, channels,
                      {"quarter_car": qc} if qc is not None else {})


def law_checks(cfg: Node, base_dir: Path) -> list[str]:
    """Rules across keys: each law's own ``check``, a demand for a law that
    needs one, the channels the sim bench provides."""
    if not isinstance(cfg.get("parameters"), LuGreParams) or not isinstance(cfg.safety.get("I_max"), float):
        return []
    ctx = law_context(cfg, base_dir)
    errors: list[str] = []
    sim = cfg.backend.get("type") == "sim" if cfg.get("backend") is not None else False
    for section, kind, key in SECTIONS:
        node = cfg.get(section)
        if node is None or node.get(key) is None:
            continue
        cls = find_law(kind, node.get(key)).cls
        if cls is None:
            continue
        errors += [f"{section}.{e}" for e in cls.check(node, ctx)]
        missing = [c for c in getattr(cls, "channels", ()) if c not in ctx.channels]
        if sim and missing:
            errors.append(f"{section}.{key}: {node.get(key)!r} needs channel(s) {', '.join(missing)}, which the "
                          f"sim bench (plant.bench: {cfg.plant.bench}) does not provide "
                          f"(it has: {', '.join(ctx.channels) or 'none'})")
        if kind == "current" and getattr(cls, "needs_demand", False) and cfg.get("demand") is None:
            errors.append(f"demand: missing required section: inverse.law {node.get(key)!r} inverts a "
                          f"desired force (demand.type: one of {', '.join(BUILTIN['demand'])}, or a plugin)")
    return errors


def laws_report(cfg: Node | None = None) -> list[str]:
    """``mrctl check``'s lines: the laws a config uses with their source and
    keys, then every law installed (built-in or entry point)."""
    lines: list[str] = []
    if cfg is not None:
        for section, kind, key in SECTIONS:
            node = cfg.get(section)
            if node is None:
                lines.append(f"{section}: none (the current law decides the current)")
                continue
            info = find_law(kind, node.get(key))
            keys = ", ".join(f"{k} = {node.get(k)!r}" for k in node if k != key)
            lines.append(f"{section}.{key}: {info.name} ({info.source}){': ' + keys if keys else ''}")
    for section, kind, key in SECTIONS:
        lines.append(f"available for {section}.{key}:")
        for info in all_laws(kind):
            if info.cls is None:
                lines.append(f"  {info.name}: REFUSED: {info.error}")
                continue
            params = ", ".join(info.cls.params) or "no keys"
            lines.append(f"  {info.name} [{info.source}] {info.cls.summary} (keys: {params})")
    return lines


def laws_markdown() -> str:
    """Every installed law's keys as docs/config.md's tables, with its
    source (``mrctl check --laws``): a plugin's reference, made like the built-ins'."""
    lines: list[str] = []
    for section, kind, key in SECTIONS:
        for i in all_laws(kind):
            lines.append(f"#### `{section}.{key}: {i.name}` ({i.source})")
            lines.append("")
            if i.cls is None:
                lines += [f"Refused: {i.error}", ""]
                continue
            lines += [i.cls.summary or "(no summary)", ""]
            table = schema_markdown({section: Section(dict(i.cls.params))}).split("\n")[2:]
            lines += table if i.cls.params else ["(no keys)", ""]
    return "\n".join(lines)

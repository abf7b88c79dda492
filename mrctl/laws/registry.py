"""The one table of law names: built-ins, entry-point plugins, ``module:Class``.

``demand.type`` names a :class:`~mrctl.laws.base.DemandLaw`, ``inverse.law``
a :class:`~mrctl.laws.base.CurrentLaw` (an inverse law, or one that decides
the current directly). A name resolves, in this order, to

1. a built-in law (:data:`BUILTIN`);
2. a law an installed package declares as an entry point (pluginlib's way,
   through :mod:`importlib.metadata`): group ``mrctl.demand_laws`` for demand
   laws, ``mrctl.inverse_laws`` and ``mrctl.current_laws`` for current laws;
   the entry point's name is the YAML name. Loaded when first named (or
   listed by ``mrctl check``), then cached;
3. ``package.module:Class``, imported when named.

Whatever goes wrong (a module that fails to import, an object that is not
a law class of the right kind, an entry point named like a built-in) comes
back as one line that names the entry point or the class: the config
engine reports it at its key (``mrctl check``, exit 2), never a traceback.
"""

from __future__ import annotations

import importlib
import os
import sys
import threading
from dataclasses import dataclass
from typing import Any, Mapping

from mrctl.laws.base import CurrentLaw, DemandLaw, Law
from mrctl.laws.closed import ClosedLoopInverse
from mrctl.laws.demand import ConstantForce, FromFile, Viscous
from mrctl.laws.inverse import ConstantCurrent, PaperInverse, ScheduleCurrent, SmoothInverse
from mrctl.laws.semiactive import LQR, ClippedOptimal, Groundhook, GroundhookOnOff, Skyhook, SkyhookOnOff
from mrctl.util.schema import Bool, Custom, FilePath, Num, Section, Str, short_repr

#: kind → entry-point groups
GROUPS: dict[str, tuple[str, ...]] = {
    "demand": ("mrctl.demand_laws",),
    "current": ("mrctl.inverse_laws", "mrctl.current_laws"),
}
#: kind → the base class its laws derive from, and the YAML key that names them
BASES: dict[str, type[Law]] = {"demand": DemandLaw, "current": CurrentLaw}
KEYS: dict[str, str] = {"demand": "demand.type", "current": "inverse.law"}

BUILTIN: dict[str, dict[str, type[Law]]] = {
    "demand": {c.name: c for c in (Viscous, ConstantForce, FromFile, Skyhook, Groundhook, LQR)},
    "current": {c.name: c for c in (PaperInverse, SmoothInverse, ClosedLoopInverse, ConstantCurrent, ScheduleCurrent,
                                    SkyhookOnOff, GroundhookOnOff, ClippedOptimal)},
}

_FIELDS = (Num, Str, Bool, Custom, FilePath, Section)


@dataclass(frozen=True)
class LawInfo:
    """One name a YAML file may use, and where it comes from."""

    name: str
    kind: str  #: "demand" or "current"
    source: str  #: "built-in", "entry point <dist> (<group>: <value>)" or "module:Class"
    cls: type[Law] | None = None
    error: str | None = None  #: why it cannot be used (cls is then None)
    target: str = ""  #: an entry point's ``module:Class``


def _unimplemented(obj: type) -> list[str]:
    """The per-tick methods of the law API that ``obj`` leaves to the base
    class (which raises): ``force`` for a demand law, ``current`` for a
    current law. Looked up in the classes' own dicts, compiled or not."""
    missing = []
    for name, owner in (("force", DemandLaw), ("current", CurrentLaw)):
        if issubclass(obj, owner):
            mro = obj.__mro__
            if not any(name in vars(c) for c in mro[:mro.index(owner)]):
                missing.append(name)
    return missing


def check_law_class(obj: Any, kind: str) -> str | None:
    """Why ``obj`` is not a usable law of ``kind``, or None if it is."""
    base = BASES[kind]
    if not (isinstance(obj, type) and issubclass(obj, Law)):
        return f"{obj!r} is not a law class (subclass mrctl.laws.base.{base.__name__})"
    if not issubclass(obj, base):
        other = "DemandLaw" if issubclass(obj, DemandLaw) else type(obj).__name__
        return (f"{obj.__module__}.{obj.__qualname__} is a {other}; {KEYS[kind]} needs a "
                f"subclass of mrctl.laws.base.{base.__name__}")
    missing = _unimplemented(obj)
    if missing:
        return f"{obj.__module__}.{obj.__qualname__} is abstract (implement {', '.join(missing)})"
    params = getattr(obj, "params", None)
    if not isinstance(params, Mapping):
        return f"{obj.__qualname__}.params must be a mapping of schema fields, got {type(params).__name__}"
    for key, spec in params.items():
        if not isinstance(key, str) or not isinstance(spec, _FIELDS):
            return (f"{obj.__qualname__}.params[{key!r}] is not a schema field "
                    f"(mrctl.util.schema: Num, Str, Bool, Custom, FilePath, Section)")
    if not isinstance(getattr(obj, "channels", ()), tuple):
        return f"{obj.__qualname__}.channels must be a tuple of channel names"
    return None


#: seconds a plugin's import may take before it is refused (a real one takes
#: well under one); ``$MRCTL_PLUGIN_IMPORT_TIMEOUT_S`` overrides it
IMPORT_TIMEOUT_S = 10.0
#: imports that did not finish in time, by module: never waited for twice
_HUNG: dict[str, threading.Thread] = {}


def import_timeout_s() -> float:
    """The bound on one plugin import (:data:`IMPORT_TIMEOUT_S`, or the environment's)."""
    try:
        v = float(os.environ.get("MRCTL_PLUGIN_IMPORT_TIMEOUT_S", IMPORT_TIMEOUT_S))
    except ValueError:
        return IMPORT_TIMEOUT_S
    return v if 0 < v < 1e6 else IMPORT_TIMEOUT_S


def _import_bounded(module: str) -> Any:
    """``importlib.import_module(module)`` in a daemon thread, waited for at
    most :func:`import_timeout_s`: a plugin whose import never returns must
    not block a start-up or the reload forever, and whatever it raises
    (``SystemExit`` included) comes back as an ImportError here instead of
    ending the process or the thread that asked."""
    hung = _HUNG.get(module)
    if hung is not None and hung.is_alive():
        raise ImportError(f"its import from an earlier attempt has not finished "
                          f"(still running after {import_timeout_s():g} s)")
    box: dict[str, Any] = {}

    def work() -> None:
        try:
            box["module"] = importlib.import_module(module)
        except BaseException as exc:  # noqa: BLE001 - SystemExit, KeyboardInterrupt: all are the plugin's
            box["error"] = exc

    t = threading.Thread(target=work, name=f"mrctl-import-{module}"[:60], daemon=True)
    t.start()
    t.join(import_timeout_s())
    if t.is_alive():
        _HUNG[module] = t
        raise ImportError(f"its import did not finish within {import_timeout_s():g} s (refused; "
                          f"$MRCTL_PLUGIN_IMPORT_TIMEOUT_S sets the bound)")
    if "error" in box:
        exc = box["error"]
        if isinstance(exc, Exception):
            raise ImportError(f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__)
        args = ", ".join(short_repr(a) for a in exc.args)
        raise ImportError(f"{type(exc).__name__}({args}) raised at import")
    return box["module"]


def _load(target: str, kind: str) -> tuple[type[Law] | None, str | None]:
    """Import ``package.module:Class`` (bounded in time: :func:`_import_bounded`) and check it."""
    module, _, qual = target.partition(":")
    if not module or not qual:
        return None, f"{short_repr(target)}: write package.module:Class"
    try:
        obj: Any = sys.modules.get(module) if _imported(module) else _import_bounded(module)
        for part in qual.split("."):
            obj = getattr(obj, part)
    except ImportError as exc:
        msg = str(exc) if not exc.name else f"{type(exc).__name__}: {exc}"
        return None, f"cannot load {short_repr(target)}: {msg}"
    except Exception as exc:  # noqa: BLE001 - a plugin's attribute may raise anything
        return None, f"cannot load {short_repr(target)}: {type(exc).__name__}: {exc}"
    why = check_law_class(obj, kind)
    return (None, why) if why else (obj, None)


def _imported(module: str) -> bool:
    """Whether ``module`` is fully imported already (no thread needed)."""
    mod = sys.modules.get(module)
    spec = getattr(mod, "__spec__", None)
    return mod is not None and not getattr(spec, "_initializing", False)


def _unknown(kind: str, name: str, eps: dict[str, LawInfo]) -> str:
    """The message for a name nothing provides: the known ones, by group."""
    semi = [n for n, c in BUILTIN[kind].items() if c.__module__ == "mrctl.laws.semiactive"]
    core = [n for n in BUILTIN[kind] if n not in semi]
    plugins = [n for n, i in eps.items() if i.error is None]
    return (f"{name!r} not allowed (allowed: {', '.join(core)}); semi-active: {', '.join(semi)}; "
            f"plugins: {', '.join(plugins) or 'none installed'}; or a class as package.module:Class")


class _Registry:
    """Entry points listed once, each loaded when first asked for."""

    def __init__(self) -> None:
        self._eps: dict[str, dict[str, LawInfo]] | None = None
        self._loaded: dict[tuple[str, str], LawInfo] = {}

    def clear(self) -> None:
        """Forget what was listed and loaded (tests; a package installed meanwhile)."""
        self._eps = None
        self._loaded.clear()

    def entry_points(self, kind: str) -> dict[str, LawInfo]:
        """The entry points of ``kind`` by name, not yet loaded (``cls`` None);
        refused ones (a clash) carry their ``error``."""
        if self._eps is None:
            self._eps = {k: self._scan(k) for k in GROUPS}
        return self._eps[kind]

    @staticmethod
    def _scan(kind: str) -> dict[str, LawInfo]:
        from importlib import metadata  # only when a name is not built in: ~8 ms of start-up otherwise

        out: dict[str, LawInfo] = {}
        for group in GROUPS[kind]:
            for ep in metadata.entry_points(group=group):
                dist = getattr(getattr(ep, "dist", None), "name", None) or "?"
                source = f"entry point {dist} ({group}: {ep.name} = {ep.value})"
                err = None
                if ep.name in BUILTIN[kind]:
                    err = f"{source} clashes with the built-in law {ep.name!r}: rename the entry point"
                elif ":" in ep.name:
                    err = f"{source}: an entry point's name must not contain ':'"
                elif ep.name in out:  # two plugins, one name: neither is guessed
                    err = f"{source}: the name {ep.name!r} is also declared by {out[ep.name].source}"
                out[ep.name] = LawInfo(ep.name, kind, source, None, err, ep.value)
        return out

    def find(self, kind: str, name: str) -> LawInfo:
        """Resolve one YAML name (built-in, entry point or module:Class)."""
        cls = BUILTIN[kind].get(name)
        if cls is not None:
            return LawInfo(name, kind, "built-in", cls)
        hit = self._loaded.get((kind, name))
        if hit is not None:
            return hit
        eps = self.entry_points(kind)
        if name in eps:
            info = eps[name]
            if info.error is None:
                cls, err = _load(info.target, kind)
                info = LawInfo(name, kind, info.source, cls,
                               None if err is None else f"{name!r} ({info.source}): {err}")
        elif ":" in name:
            cls, err = _load(name, kind)
            info = LawInfo(name, kind, "module:Class", cls, err)
        else:
            info = LawInfo(name, kind, "", None, _unknown(kind, name, eps))
        if info.cls is not None:  # a failure is tried again: the user may fix it and reload
            self._loaded[(kind, name)] = info
        return info

    def all(self, kind: str) -> list[LawInfo]:
        """Every built-in and entry-point law of ``kind``, entry points loaded."""
        return ([LawInfo(n, kind, "built-in", c) for n, c in BUILTIN[kind].items()]
                + [self.find(kind, n) if i.error is None else i for n, i in self.entry_points(kind).items()])


REGISTRY = _Registry()


def find_law(kind: str, name: str) -> LawInfo:
    """``kind`` is "demand" or "current"; see :class:`_Registry.find`."""
    return REGISTRY.find(kind, name)


def law_class(kind: str, name: str) -> type[Law]:
    """The class a validated config names (KeyError with the reason otherwise)."""
    info = REGISTRY.find(kind, name)
    if info.cls is None:
        raise KeyError(info.error)
    return info.cls


def all_laws(kind: str) -> list[LawInfo]:
    """Built-ins and installed entry points (``mrctl check``)."""
    return REGISTRY.all(kind)


def demand_laws() -> dict[str, type[DemandLaw]]:
    """The built-in demand laws by YAML name (``demand.type``)."""
    return dict(BUILTIN["demand"])  # type: ignore[arg-type]


def current_laws() -> dict[str, type[CurrentLaw]]:
    """The built-in current laws by YAML name (``inverse.law``)."""
    return dict(BUILTIN["current"])  # type: ignore[arg-type]

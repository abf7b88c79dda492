"""Which build of the tick runs: mypyc-compiled or pure Python.

The modules in :data:`COMPILED_MODULES` are plain type-hinted Python that
``setup.py`` compiles with mypyc at install (docs/design.md, "The compiled
core"). The same sources run interpreted when no compiler was there at
install, or when ``MRCTL_PURE_PYTHON=1`` asks for it at run time: then
:func:`install_pure_finder` (called by ``mrctl/__init__.py`` before anything
else of mrctl is imported) makes Python load those modules' ``.py`` files
instead of their compiled extensions, and refuse the C extensions of
:data:`C_EXTENSIONS` (their Python twins run instead). Both builds compute the same currents
bit for bit (tests/test_builds.py).

Kept free of imports from the rest of mrctl: ``setup.py`` reads the module
list from this file before mrctl is installed.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys
from types import ModuleType
from typing import Sequence

#: the modules mypyc compiles: the tick's good path and what it calls per tick
COMPILED_MODULES: tuple[str, ...] = (
    "mrctl.model.params",
    "mrctl.model.lugre",
    "mrctl.model.plant",
    "mrctl.model.bench",
    "mrctl.laws.guard",
    "mrctl.laws.base",
    "mrctl.laws.inverse",
    "mrctl.laws.closed",
    "mrctl.laws.demand",
    "mrctl.laws.semiactive",
    "mrctl.estimation.observer",
    "mrctl.estimation.lead",
    "mrctl.core.safety",
    "mrctl.core.controller",
    "mrctl.core.offline",
)

#: C extensions built beside them, with the same all-or-nothing fallback: each
#: has a Python twin that writes the same bytes (the run log's row formatter,
#: mrctl/runlog/rowtext.py)
C_EXTENSIONS: tuple[str, ...] = (
    "mrctl.runlog._rowtext",
)

#: the environment switch that forces the interpreted build
PURE_ENV = "MRCTL_PURE_PYTHON"

COMPILED = "compiled"
PURE = "pure Python"


def pure_requested() -> bool:
    """``MRCTL_PURE_PYTHON`` is set to something other than '', '0' or 'no'."""
    return os.environ.get(PURE_ENV, "").strip().lower() not in ("", "0", "no", "false")


class _PureFinder:
    """A meta-path finder that loads the compiled modules from their sources
    and refuses the C extensions (their callers fall back to Python)."""

    def find_spec(self, name: str, path: Sequence[str] | None, target: ModuleType | None = None
                  ) -> importlib.machinery.ModuleSpec | None:
        if name in C_EXTENSIONS:  # the interpreted build uses the Python twin
            raise ModuleNotFoundError(f"{name}: not loaded with {PURE_ENV} set", name=name)
        if name not in COMPILED_MODULES or not path:
            return None
        leaf = name.rpartition(".")[2]
        for folder in path:
            src = os.path.join(folder, leaf + ".py")
            if os.path.isfile(src):
                return importlib.util.spec_from_file_location(name, src)
        return None


def install_pure_finder() -> None:
    """With ``MRCTL_PURE_PYTHON`` set, load the compiled modules' sources."""
    if pure_requested() and not any(isinstance(f, _PureFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, _PureFinder())


def module_build(module: ModuleType) -> str:
    """COMPILED if ``module`` was loaded from a mypyc extension, else PURE."""
    f = getattr(module, "__file__", "") or ""
    return COMPILED if f.endswith(tuple(importlib.machinery.EXTENSION_SUFFIXES)) else PURE


def tick_build() -> str:
    """The build of the tick that runs in this process (the controller's module decides)."""
    from mrctl.core import controller

    return module_build(controller)


def build_notice() -> str | None:
    """One line for stderr at start when the compiled build was wanted but is
    not installed (no compiler or headers at install); None otherwise."""
    if pure_requested() or tick_build() == COMPILED:
        return None
    return (f"mrctl: running the pure-Python build (the compiled tick was not built at install: "
            f"no C compiler or Python headers?); it is correct but ~5x slower per tick "
            f"(set {PURE_ENV}=1 to silence this)")

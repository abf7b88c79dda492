"""Builds the compiled tick with mypyc (docs/design.md, "The compiled core").

Everything else is in pyproject.toml. The modules listed in mrctl/build.py
are compiled with mypyc, and its C extensions beside them; with
MRCTL_PURE_PYTHON=1 at install, or when the compile fails (no C compiler or
Python headers), the same sources are installed to run interpreted, and
mrctl says so on stderr when it starts.
"""

import ast
import os
import sys
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

HERE = Path(__file__).resolve().parent


def _build_lists() -> tuple[list[str], list[str]]:
    """The sources of COMPILED_MODULES (for mypyc) and the names of C_EXTENSIONS,
    from mrctl/build.py read without importing mrctl; both empty with PURE_ENV set."""
    tree = ast.parse((HERE / "mrctl" / "build.py").read_text())
    found = {}
    for node in tree.body:
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            target = node.targets[0] if isinstance(node, ast.Assign) else node.target
            if isinstance(target, ast.Name) and target.id in ("COMPILED_MODULES", "C_EXTENSIONS", "PURE_ENV"):
                found[target.id] = ast.literal_eval(node.value)
    if os.environ.get(found["PURE_ENV"], "").strip().lower() not in ("", "0", "no", "false"):
        return [], []
    return [m.replace(".", "/") + ".py" for m in found["COMPILED_MODULES"]], list(found["C_EXTENSIONS"])


class OptionalBuildExt(build_ext):
    """A failed compile leaves the pure-Python build, never a failed install."""

    def run(self) -> None:
        try:
            super().run()
        except Exception as exc:  # noqa: BLE001 - any toolchain failure
            # all or nothing: a module's extension without the shared library
            # they all load would fail to import instead of running interpreted
            for ext in self.extensions:
                for built in (Path(self.get_ext_fullpath(ext.name)),
                              Path(self.build_lib) / self.get_ext_filename(ext.name)):
                    built.unlink(missing_ok=True)
            print(f"mrctl: the compiled tick could not be built ({exc}); installing the pure-Python build",
                  file=sys.stderr)


def _extensions() -> list:
    mods, c_exts = _build_lists()
    if not mods:
        return []
    try:
        from mypyc.build import mypycify
    except ImportError as exc:
        print(f"mrctl: mypyc not available ({exc}); installing the pure-Python build", file=sys.stderr)
        return []
    try:
        exts = mypycify(mods, opt_level="3", debug_level="0")
    except BaseException as exc:  # noqa: BLE001 - mypy reports type errors with SystemExit
        print(f"mrctl: mypyc refused the tick's modules ({exc}); installing the pure-Python build",
              file=sys.stderr)
        return []
    # the C extensions (e.g. the run log's row formatter), beside mypyc's: one build, all or nothing
    exts += [Extension(name, [name.replace(".", "/") + ".c"], extra_compile_args=["-O2"]) for name in c_exts]
    for ext in exts:
        # the compiled build must equal the interpreted one bit for bit: no fused
        # multiply-add, no fast-math (CPython's own float arithmetic does neither)
        ext.extra_compile_args = [*ext.extra_compile_args, "-ffp-contract=off", "-fno-fast-math"]
    return exts


setup(ext_modules=_extensions(), cmdclass={"build_ext": OptionalBuildExt})

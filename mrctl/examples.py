"""``mrctl examples [DIR]``: the files a pip install ships besides the code.

The example experiments (``config/experiments/*.yaml``), hil_sim's bench
configs (``config/hil_*.yaml``), the systemd units and the tmpfiles.d entry
for the device-lock directory (``systemd/``) and the reference docs
(``docs/``, the targets of README's links) live in the package
(``mrctl/data/``, whose ``config``, ``systemd`` and ``docs`` are symlinks to
the source tree's top-level directories, copied into the wheel when it is built),
so they exist wherever mrctl is installed. This copies them out, with the
same layout as the source tree, so README's commands (``mrctl run
config/experiments/fig5.yaml``) work in DIR; and README.md itself, from the
package's metadata (the units' ``Documentation=`` names it, docs/install.md).

It never follows a symlink it did not create: DIR, and every folder and
file under it, is opened relative to its parent with ``O_NOFOLLOW``, so a
symlinked ``DIR/config`` (or ``DIR`` itself) is refused by name before
anything is written, and ``--force`` replaces a symlink in a file's place,
never what it points at.
"""

from __future__ import annotations

import errno
import importlib.metadata
import importlib.resources
import os
import stat
from pathlib import Path

from mrctl.errors import BadInput

__all__ = ["example_files", "copy_examples"]

_PATTERNS = ("config/**/*.yaml", "systemd/*.service", "systemd/*.conf", "docs/*.md", "docs/*.xml", "docs/img/*.png")

#: what the copied README says first: its links to docs/ work in DIR, what is not shipped is named
_README_NOTE = ("> Copied by `mrctl examples` from the installed mrctl {version}: the links to `docs/` open the\n"
                "> reference installed with it (also `mrctl docs TOPIC`); `bench/`, `examples/`, `firmware/` and\n"
                "> `tests/`, named below, are in the source repository (the source tree), not in the package.\n\n")


def _data() -> Path:
    return Path(str(importlib.resources.files("mrctl") / "data"))


def example_files() -> list[str]:
    """Every shipped example, as a path relative to the data directory."""
    root = _data()
    return sorted({str(p.relative_to(root)) for pat in _PATTERNS for p in root.glob(pat) if p.is_file()})


def _readme() -> str | None:
    src = Path(__file__).resolve().parents[1] / "README.md"  # a source checkout
    if src.is_file():
        return src.read_text(encoding="utf-8")
    try:
        meta = importlib.metadata.metadata("mrctl")
    except importlib.metadata.PackageNotFoundError:
        return None
    body = meta.get_payload() if hasattr(meta, "get_payload") else None  # the long description
    return body or meta.get("Description") or None


def _refuse_link(path: Path) -> BadInput:
    try:
        target = f" (to {os.readlink(path)})"
    except OSError:
        target = ""
    return BadInput(f"{path}: is a symlink{target}; mrctl examples never follows a symlink it did not create: "
                    "nothing written there (remove it, or give another DIR)")


def _check(dest: Path, rels: list[str], force: bool) -> None:
    """Before anything is written: no symlink at DIR or on the way to a file,
    no file where a folder goes, no existing file unless ``force``
    (``BadInput`` naming the first, and how many exist)."""
    clash: list[str] = []
    for rel in rels:
        here = dest
        for part in (".", *Path(rel).parts):
            here = here / part if part != "." else here
            try:
                st = os.lstat(here)
            except FileNotFoundError:
                break
            if stat.S_ISLNK(st.st_mode):
                raise _refuse_link(here)
            if here != dest / rel and not stat.S_ISDIR(st.st_mode):
                raise BadInput(f"{here}: exists and is not a directory; nothing written")
            if here == dest / rel:
                if stat.S_ISDIR(st.st_mode):
                    raise BadInput(f"{here}: is a directory where a file goes; nothing written")
                clash.append(rel)
    if clash and not force:
        raise BadInput(f"{dest}: {len(clash)} file(s) exist, e.g. {dest / clash[0]}; "
                       f"nothing written (pass --force to overwrite them)")


def _open_dir(name: str, dir_fd: int | None, shown: Path) -> int:
    """The folder ``name`` (in ``dir_fd``), created if missing, opened without following a symlink."""
    try:
        os.mkdir(name, 0o755, dir_fd=dir_fd)
    except FileExistsError:
        pass
    try:
        return os.open(name, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=dir_fd)
    except OSError as exc:
        if exc.errno == errno.ELOOP or (exc.errno == errno.ENOTDIR and os.path.islink(shown)):
            raise _refuse_link(shown) from None
        raise BadInput(f"{shown}: cannot use it as a folder: {exc.strerror or exc}") from None


def _write(dir_fd: int, name: str, data: bytes, force: bool, shown: Path) -> None:
    """``data`` as the new file ``name`` in ``dir_fd``; with ``force`` what is
    there (a file or a symlink, never what a link points at) is replaced."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    if force:
        try:
            if stat.S_ISDIR(os.stat(name, dir_fd=dir_fd, follow_symlinks=False).st_mode):
                raise BadInput(f"{shown}: is a directory where a file goes")
            os.unlink(name, dir_fd=dir_fd)
        except FileNotFoundError:
            pass
    try:
        fd = os.open(name, flags, 0o644, dir_fd=dir_fd)
    except FileExistsError:
        raise BadInput(f"{shown}: appeared while copying; not overwritten (pass --force)") from None
    except OSError as exc:
        raise BadInput(f"{shown}: cannot write: {exc.strerror or exc}") from None
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)


def copy_examples(dest: Path, force: bool = False) -> list[str]:
    """Copy every example (and README.md) under ``dest``; returns the paths
    written, relative to it. Refuses (``BadInput``, nothing written) if any
    would overwrite a file, unless ``force``, or if a symlink stands at
    ``dest`` or on the way to a file (never followed, ``--force`` or not)."""
    root = _data()
    items: list[tuple[str, bytes]] = [(rel, (root / rel).read_bytes()) for rel in example_files()]
    if not items:
        raise BadInput(f"no example files found in {root}: is mrctl installed completely?")
    readme = _readme()
    if readme:
        from mrctl import __version__

        items.append(("README.md", (_README_NOTE.format(version=__version__) + readme).encode("utf-8")))
    if dest.exists() and not dest.is_dir() and not dest.is_symlink():
        raise BadInput(f"{dest}: exists and is not a directory")
    _check(dest, [rel for rel, _ in items], force)
    dest.parent.mkdir(parents=True, exist_ok=True)  # the folders above DIR are the user's path: followed
    if dest.name in ("", ".", ".."):
        top = os.open(dest, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    else:
        parent = os.open(dest.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            top = _open_dir(dest.name, parent, dest)
        finally:
            os.close(parent)
    try:
        for rel, data in items:
            parts = Path(rel).parts
            fds = [top]
            try:
                for i, part in enumerate(parts[:-1]):
                    fds.append(_open_dir(part, fds[-1], dest.joinpath(*parts[:i + 1])))
                _write(fds[-1], parts[-1], data, force, dest / rel)
            finally:
                for fd in fds[1:]:
                    os.close(fd)
    finally:
        os.close(top)
    return [rel for rel, _ in items]

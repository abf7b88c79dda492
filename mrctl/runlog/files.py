"""Where a run log goes: created safely, never by surprise, never through a symlink.

* :func:`check_log_path` says, without touching anything, whether ``--out``
  can be used: not a ``.json`` name (the sidecar would overwrite its own
  CSV), not a directory, and neither the CSV nor its sidecar may exist
  unless ``force``; its directory must exist unless ``mkdir`` (or it is
  ``runs/``: :func:`mrctl.util.files.check_out_parent`).
* :func:`create_log` creates the CSV with ``O_CREAT | O_EXCL | O_NOFOLLOW``:
  a symlink planted at the path is never followed; with ``force`` an
  existing file (or symlink) is unlinked first, its target untouched.
* :func:`write_json` writes a sidecar through a temp file (created the same
  way) and ``os.replace`` (which replaces a symlink, never follows it). The
  start-up sidecar is padded with spaces to ``reserve`` bytes (valid JSON),
  so that when the disk is full at the end, the final sidecar still fits: it
  is then written over the reservation in place, using no new blocks.
"""

from __future__ import annotations

import json
import os
import stat
import threading
from pathlib import Path
from typing import Any, BinaryIO, Mapping

from mrctl.errors import BadInput
from mrctl.util.files import check_out_parent
from mrctl.util.jsonutil import jsonable

__all__ = ["SIDECAR_RESERVE_BYTES", "sidecar_path", "check_log_path", "create_log", "write_json", "fsync_dir"]

#: the start-up sidecar's size on disk: room for the final one on a full disk
SIDECAR_RESERVE_BYTES = 64 * 1024

_CREATE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC


def sidecar_path(path: str | os.PathLike[str]) -> Path:
    """The JSON sidecar beside a run CSV: same stem, ``.json`` suffix."""
    return Path(path).with_suffix(".json")


def check_log_path(path: str | os.PathLike[str], force: bool = False, mkdir: bool = False) -> Path:
    """``BadInput`` if ``path`` cannot be a new run log (see the module doc),
    or its directory is missing and may not be created
    (:func:`mrctl.util.files.check_out_parent`); touches nothing."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        raise BadInput(f"{p}: the run log is a CSV; a .json name would be its own sidecar's")
    side = sidecar_path(p)
    for q, what in ((p, "the run log"), (side, f"the sidecar of {p.name}")):
        if q.is_dir() and not q.is_symlink():
            raise BadInput(f"{q}: is a directory; --out names the run log's CSV file" if q == p
                           else f"{q}: {what} would go there, but it is a directory")
        if os.path.lexists(q) and not force:
            kind = "a symlink" if q.is_symlink() else "a file"
            raise BadInput(f"{q}: {what} would replace {kind} that exists; refusing (pass --force to replace it)")
    check_out_parent(p, mkdir)
    return p


def create_log(path: str | os.PathLike[str], force: bool = False, mkdir: bool = False) -> BinaryIO:
    """Create the run log's CSV (empty) and return it open for binary
    writing; with ``force`` an existing CSV and sidecar are unlinked first.
    ``BadInput`` naming the path if it cannot be created, or if its
    directory is missing (unless ``mkdir``, or ``runs/``)."""
    p = check_log_path(path, force, mkdir)
    if force:
        for q in (p, sidecar_path(p)):
            try:
                os.unlink(q)  # a symlink goes; what it points at stays
            except FileNotFoundError:
                pass
            except OSError as exc:
                raise BadInput(f"{q}: cannot replace it: {exc.strerror or exc}") from None
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInput(f"{p}: cannot create its directory {p.parent}: {exc.strerror or exc}") from None
    try:
        fd = os.open(p, _CREATE, 0o644)
    except FileExistsError:
        raise BadInput(f"{p}: appeared while starting; refusing to replace it (pass --force)") from None
    except OSError as exc:
        raise BadInput(f"{p}: cannot create the run log: {exc.strerror or exc}") from None
    return os.fdopen(fd, "wb", buffering=0)


def write_json(path: str | os.PathLike[str], data: Mapping[str, Any], reserve: int = 0) -> None:
    """Write ``data`` as strict JSON to ``path``, atomically (temp file, fsync,
    ``os.replace``), padded with spaces to ``reserve`` bytes. If that fails
    (a full disk) and the file already there is large enough (a reservation),
    overwrite it in place instead. Raises the first ``OSError`` if neither works."""
    p = Path(path)
    body = (json.dumps(jsonable(data), indent=2, allow_nan=False) + "\n").encode()
    text = body[:-1] + b" " * (reserve - len(body)) + b"\n" if reserve > len(body) else body
    tmp = p.with_name(f".{p.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        fd = os.open(tmp, _CREATE, 0o644)
        try:
            _write_all(fd, text, 0)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, p)
    except OSError:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if not _overwrite_in_place(p, body):
            raise
        return
    fsync_dir(p.parent)


def _write_all(fd: int, data: bytes, offset: int) -> None:
    view = memoryview(data)
    done = 0
    while done < len(data):
        n = os.pwrite(fd, view[done:], offset + done)
        if n <= 0:
            raise OSError(f"pwrite returned {n}")
        done += n


def _overwrite_in_place(p: Path, body: bytes) -> bool:
    """Write ``body`` over the regular file at ``p`` if it is at least as long
    (the rest becomes spaces): no new blocks needed. True if it worked."""
    try:
        fd = os.open(p, os.O_WRONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size < len(body):
            return False
        _write_all(fd, body[:-1] + b" " * (st.st_size - len(body)) + b"\n", 0)
        os.fsync(fd)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def fsync_dir(directory: Path) -> None:
    """Best effort: make a directory entry (new/renamed file) durable."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)

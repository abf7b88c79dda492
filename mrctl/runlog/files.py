"""Where a run log goes: created safely, never by surprise, never through a symlink.

* :func:`check_log_path` says, without touching anything, whether ``--out``
  can be used: not a ``.json`` name (the sidecar would overwrite its own
  CSV), not a directory, and neither the CSV nor its sidecar may exist
  unless ``force``; its directory must exist unless ``mkdir`` (or it is
  ``runs/``: :func:`mrctl.util.files.check_out_parent`).
* :func:`create_log` creates the CSV with ``O_CREAT | O_EXCL | O_NOFOLLOW``:
  a symlink planted at the path is never followed; with ``force`` an
  existing file (or symlink) is unlinked first, its target untouched. The
  sidecar's name is taken the same way at once (an empty file until the
  first :func:`write_json`): two logs with one stem (``run.csv`` and
  ``run.tsv``) cannot share one sidecar; the second is refused.
* :func:`check_output_path` and :func:`write_outputs`: the same rules for
  the other files mrctl writes (identify's parameters and summary, report
  figures): an existing file is refused unless ``force``, a symlink is never
  followed, an input is never an output; the files appear whole or not at all.
* :func:`write_json` writes a sidecar through a temp file (created the same
  way) and ``os.replace`` (which replaces a symlink, never follows it). The
  start-up sidecar is padded with spaces to ``reserve`` bytes (valid JSON),
  so that when the disk is full at the end, the final sidecar still fits: it
  is then written over the reservation in place, using no new blocks.
"""

from __future__ import annotations

import errno
import json
import os
import stat
import threading
from pathlib import Path
from typing import Any, BinaryIO, Mapping, Sequence

from mrctl.errors import BadInput
from mrctl.util.files import check_out_parent, refuse_inputs, refuse_special
from mrctl.util.jsonutil import jsonable

__all__ = ["SIDECAR_RESERVE_BYTES", "sidecar_path", "check_log_path", "create_log", "write_json", "fsync_dir",
           "check_output_path", "write_outputs", "drop_log"]

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
    if not str(path):
        raise BadInput("--out '': an empty name; give the run log's file name (or leave --out out for no log)")
    if p.suffix.lower() == ".json":
        raise BadInput(f"{p}: the run log is a CSV; a .json name would be its own sidecar's")
    check_output_path(p, force, what="the run log")
    check_output_path(sidecar_path(p), force, what=f"the sidecar of {p.name}")
    check_out_parent(p, mkdir)
    return p


def check_output_path(path: str | os.PathLike[str], force: bool = False,
                      inputs: Sequence[str | os.PathLike[str]] = (), what: str = "the output") -> Path:
    """``BadInput`` unless ``path`` can be a new output file: not empty, not a
    directory, not one of ``inputs`` (not even with ``force``, nor through a
    symlink), not an existing file or symlink unless ``force``, under a
    parent that is (or can be made) a directory. Touches nothing."""
    if not str(path):
        raise BadInput(f"'': an empty file name for {what}")
    p = Path(path)
    refuse_inputs([p], inputs, what)
    if p.is_dir() and not p.is_symlink():
        raise BadInput(f"{p}: is a directory; {what} is a file" if what != "the run log"
                       else f"{p}: is a directory; --out names the run log's CSV file")
    refuse_special([p], what)
    if os.path.lexists(p) and not force:
        kind = "a symlink" if p.is_symlink() else "a file"
        raise BadInput(f"{p}: {what} would replace {kind} that exists; refusing (pass --force to replace it)")
    parent = p.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise BadInput(f"{p}: cannot create it: {parent} is not a directory")
    return p


def write_outputs(items: Sequence[tuple[str | os.PathLike[str], bytes]], force: bool = False,
                  mkdir: bool = False) -> None:
    """Write each ``(path, bytes)`` whole or not at all: a temp file beside it
    (``O_EXCL | O_NOFOLLOW``), fsync, then linked to its name (refused if
    the name exists: another writer got there first) or, with ``force``,
    renamed over it (a symlink there is replaced, never followed). If one
    fails, the ones already written are removed: ``BadInput`` (the name is
    taken) or ``OSError``. ``mkdir``: create missing parent directories."""
    done: list[Path] = []
    try:
        for path, data in items:
            p = Path(path)
            if mkdir:
                p.parent.mkdir(parents=True, exist_ok=True)
            tmp = p.with_name(f".{p.name}.{os.getpid()}.{threading.get_ident()}.tmp")
            fd = os.open(tmp, _CREATE, 0o644)
            try:
                try:
                    _write_all(fd, data, 0)
                    os.fsync(fd)
                finally:
                    os.close(fd)
                if force:
                    os.replace(tmp, p)
                else:
                    try:
                        os.link(tmp, p, follow_symlinks=False)
                    except FileExistsError:
                        raise BadInput(f"{p}: appeared while writing; refusing to replace it (pass --force)") from None
                    except OSError as exc:  # no hard links here (vfat, some FUSE): create it exclusively instead
                        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EXDEV, errno.EMLINK, errno.ENOSYS):
                            raise
                        _create_whole(p, data)
            finally:
                try:
                    os.unlink(tmp)
                except FileNotFoundError:
                    pass
            done.append(p)
            fsync_dir(p.parent)
    except BaseException:
        for p in done:
            try:
                os.unlink(p)
            except OSError:
                pass
        raise


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
    side = sidecar_path(p)
    try:  # the sidecar's name is ours from now on: a run logging to run.tsv cannot take it
        os.close(os.open(side, _CREATE, 0o644))
    except OSError as exc:
        os.close(fd)
        os.unlink(p)
        if isinstance(exc, FileExistsError):
            raise BadInput(f"{side}: the sidecar of {p.name} appeared while starting (another run with the same "
                           "stem?); refusing to share it") from None
        raise BadInput(f"{side}: cannot create the sidecar: {exc.strerror or exc}") from None
    return os.fdopen(fd, "wb", buffering=0)


def drop_log(path: str | os.PathLike[str]) -> None:
    """Remove a run log that was created but never used (a start refused after
    :func:`create_log`): the CSV and the sidecar reservation if it is still
    the empty file create_log left (a written sidecar is never removed)."""
    p = Path(path)
    for q, only_empty in ((p, False), (sidecar_path(p), True)):
        try:
            if only_empty:
                st = os.lstat(q)
                if not stat.S_ISREG(st.st_mode) or st.st_size:
                    continue
            os.unlink(q)
        except OSError:
            pass


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


def _create_whole(p: Path, data: bytes) -> None:
    """Create ``p`` exclusively (never through a symlink) with ``data``; removed again if the write fails."""
    try:
        fd = os.open(p, _CREATE, 0o644)
    except FileExistsError:
        raise BadInput(f"{p}: appeared while writing; refusing to replace it (pass --force)") from None
    try:
        _write_all(fd, data, 0)
        os.fsync(fd)
    except OSError:
        os.close(fd)
        os.unlink(p)
        raise
    os.close(fd)


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


#: where ``mrctl run`` logs without ``--out``, under the working directory
#: (the systemd units use the same pattern under their state directory)
DEFAULT_LOG = "runs/{name}-%Y%m%d-%H%M%S.csv"


def default_log_path(name: str) -> str:
    """``runs/<name>-<date>-<time>.csv`` (the name made safe for a file name;
    ``-2``, ``-3``, … when a run of the same second has it), its directory
    created: a forgotten ``--out`` loses no experiment."""
    import re
    import time

    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "run"
    path = time.strftime(DEFAULT_LOG.format(name=safe))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    stem, n = path[: -len(".csv")] if path.endswith(".csv") else path, 1
    while os.path.lexists(path) or os.path.lexists(sidecar_path(path)):  # two runs started in one second
        n += 1
        path = f"{stem}-{n}.csv"
    return path

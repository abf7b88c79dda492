"""Reading the files a user points mrctl at, and the per-user runtime directory.

* :func:`read_regular_file`: a config, parameter set or series is read only
  if it is a regular file (``/dev/zero``, a FIFO or a terminal would be read
  without end or block forever) and at most ``max_bytes`` long.
* :func:`check_out_parent` / :func:`ensure_out_parent`: an output (``--out``)
  goes into a directory that exists; a missing one is an error naming it
  (a typo must not grow a tree, least of all as root), created only when
  asked (``--mkdir``) or when it is the conventional ``runs/`` of the
  current directory (README's commands write there).
* :func:`private_dir`: the per-user directory used without systemd
  (status socket, device locks when the shared lock directory cannot be
  used), created 0700 and trusted only if it is ours and nobody else can
  write to it: another local user who creates it first must not be able to
  plant a socket there.
"""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

from mrctl.errors import BadInput

__all__ = ["FileProblem", "read_regular_file", "not_regular", "per_user_dir", "private_dir", "MiB", "DEFAULT_OUT_DIR",
           "check_out_parent", "ensure_out_parent"]

MiB = 1 << 20


class FileProblem(BadInput):
    """A file cannot be read as input; the message says why, without the path
    (callers add it with their own context: a key path, a line).
    ``missing``: there is no such file."""

    def __init__(self, message: str, missing: bool = False) -> None:
        super().__init__(message)
        self.missing = missing


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISREG, "a regular file"), (stat.S_ISLNK, "a symlink"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory")):
        if test(mode):
            return name
    return "not a plain file"


def not_regular(path: str | os.PathLike[str]) -> str | None:
    """None if ``path`` is a regular file (symlinks followed); else what it
    is, for a message: ``"missing"``, ``"a directory"``, ``"a FIFO"``, …
    (a FIFO or device is not "no such file")."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "missing"
    except OSError as exc:
        return f"unreadable ({exc.strerror or exc})"
    return None if stat.S_ISREG(st.st_mode) else _kind(st.st_mode)


def read_regular_file(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The bytes of the regular file at ``path`` (symlinks followed), at most
    ``max_bytes``. :class:`FileProblem` if it is missing, not a regular file
    (a device, FIFO, directory …), larger, or unreadable."""
    flags = os.O_RDONLY | os.O_CLOEXEC | getattr(os, "O_NONBLOCK", 0)  # a FIFO must not block the open
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise FileProblem("no such file", missing=True) from None
    except OSError as exc:
        raise FileProblem(f"cannot read: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileProblem(f"not a regular file ({_kind(st.st_mode)})")
        if st.st_size > max_bytes:
            raise FileProblem(f"too large ({st.st_size / MiB:.1f} MiB; at most {max_bytes / MiB:g} MiB)")
        chunks: list[bytes] = []
        left = max_bytes + 1
        while left > 0:
            b = os.read(fd, min(left, MiB))
            if not b:
                break
            chunks.append(b)
            left -= len(b)
        data = b"".join(chunks)
        if len(data) > max_bytes:  # grew while being read
            raise FileProblem(f"too large (more than {max_bytes / MiB:g} MiB)")
        return data
    except OSError as exc:
        raise FileProblem(f"cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def per_user_dir() -> Path:
    """``$TMPDIR/mrctl-<uid>`` (``/tmp/mrctl-<uid>``): the fallback runtime
    directory without systemd. Not created here: see :func:`private_dir`."""
    return Path(tempfile.gettempdir()) / f"mrctl-{os.getuid()}"


def check_private_dir(path: Path) -> None:
    """``OSError`` naming the problem unless ``path`` is a directory (not a
    symlink) owned by us that nobody else can write to; one of ours that
    others could only read or enter is tightened to 0700."""
    st = os.lstat(path)
    if not stat.S_ISDIR(st.st_mode):
        raise OSError(f"{path}: exists and is {'a symlink' if stat.S_ISLNK(st.st_mode) else _kind(st.st_mode)}, "
                      f"not a directory of this user's; refusing to use it")
    if st.st_uid != os.getuid():
        raise OSError(f"{path}: owned by uid {st.st_uid}, not by this user (uid {os.getuid()}): "
                      f"someone else created it; refusing to trust it (remove it)")
    if st.st_mode & 0o022:
        raise OSError(f"{path}: writable by others (mode {stat.S_IMODE(st.st_mode):04o}): what is in it "
                      f"cannot be trusted; refusing it (remove it)")
    if stat.S_IMODE(st.st_mode) != 0o700:
        os.chmod(path, 0o700)


def private_dir(path: Path | None = None) -> Path:
    """Create (0700) or check the per-user directory; ``OSError`` if it is not
    ours alone (see :func:`check_private_dir`)."""
    p = Path(path) if path is not None else per_user_dir()
    try:
        os.mkdir(p, 0o700)
    except FileExistsError:
        pass
    check_private_dir(p)
    return p


#: the one output directory created without ``--mkdir``: ``runs/`` in the current directory
DEFAULT_OUT_DIR = Path("runs")


def check_out_parent(path: str | os.PathLike[str], mkdir: bool = False) -> Path | None:
    """The directory ``path`` needs created (None if its parent exists);
    ``BadInput`` naming the missing directory unless ``mkdir`` or it is
    :data:`DEFAULT_OUT_DIR`, or if what is there is not a directory.
    Touches nothing."""
    p = Path(path)
    parent = p.parent
    if parent.is_dir():
        return None
    if os.path.lexists(parent):
        raise BadInput(f"{p}: cannot create it: {parent} is not a directory")
    if not (mkdir or parent == DEFAULT_OUT_DIR):
        missing = parent
        while not missing.parent.is_dir() and missing.parent != missing:
            missing = missing.parent
        raise BadInput(f"{p}: directory {parent} does not exist (no {missing}); "
                       f"check the path, or pass --mkdir to create it")
    up = parent
    while not os.path.lexists(up) and up != up.parent:
        up = up.parent
    if not up.is_dir():
        raise BadInput(f"{p}: cannot create it: {up} is not a directory")
    return parent


def ensure_out_parent(path: str | os.PathLike[str], mkdir: bool = False) -> None:
    """:func:`check_out_parent`, then create the directory it allows
    (``BadInput`` naming it if that fails)."""
    d = check_out_parent(path, mkdir)
    if d is None:
        return
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInput(f"{path}: cannot create its directory {d}: {exc.strerror or exc}") from None

"""Reading the files a user points mrctl at, and the per-user runtime directory.

* :func:`read_regular_file`: a config, parameter set or series is read only
  if it is a regular file (``/dev/zero``, a FIFO or a terminal would be read
  without end or block forever) and at most ``max_bytes`` long.
* :class:`Fence` and its one function :meth:`Fence.admit`: every path a
  config, sweep, dataset description or sidecar names must lie under the
  folder of the file named on the command line (its ``config/`` tree, when
  it lies in one), ``--data-dir``, or anywhere with ``--allow-outside-paths``:
  a file from elsewhere cannot make mrctl read ``/etc/shadow``.
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

import errno
import os
import stat
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from mrctl.errors import BadInput

__all__ = ["FileProblem", "read_regular_file", "open_regular", "flock_holder", "not_regular", "per_user_dir",
           "private_dir", "MiB", "DEFAULT_OUT_DIR", "check_out_parent", "ensure_out_parent", "Fence", "fence_root",
           "CONFIG_TREE", "same_file", "refuse_inputs", "refuse_special"]

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


def open_regular(path: str | os.PathLike[str], flags: int = os.O_RDONLY, mode: int = 0o644) -> int:
    """A descriptor of the regular file at ``path``, opened without blocking
    (a FIFO would block the open, a device be read without end) and checked
    before anything is read or written; :class:`FileProblem` naming what it
    is otherwise (``missing``: no such file)."""
    try:
        fd = os.open(path, flags | os.O_CLOEXEC | getattr(os, "O_NONBLOCK", 0), mode)
    except FileNotFoundError:
        raise FileProblem("no such file", missing=True) from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise FileProblem("a symlink; refusing to follow it") from None
        if exc.errno == errno.EISDIR:
            raise FileProblem("not a regular file (a directory)") from None
        kind = not_regular(path)
        if kind is None or kind == "missing" or kind.startswith("unreadable"):
            raise FileProblem(f"cannot read: {exc.strerror or exc}") from None
        raise FileProblem(f"not a regular file ({kind})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileProblem(f"not a regular file ({_kind(st.st_mode)})")
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd


def flock_holder(fd: int) -> int | None:
    """The pid holding a ``flock`` on the file open at ``fd`` (``/proc/locks``), if one does."""
    try:
        st = os.fstat(fd)
        dev = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
        for line in Path("/proc/locks").read_text().splitlines():
            f = line.split()
            if len(f) >= 6 and f[1] == "FLOCK" and f[5] == dev and f[4].isdigit() and int(f[4]) > 0:
                return int(f[4])
    except OSError:
        pass
    return None


def read_regular_file(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The bytes of the regular file at ``path`` (symlinks followed), at most
    ``max_bytes``. :class:`FileProblem` if it is missing, not a regular file
    (a device, FIFO, directory …), larger, or unreadable."""
    fd = open_regular(path)
    try:
        st = os.fstat(fd)
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


#: a folder of this name holds one config tree (mrctl's layout: config/experiments, config/plants,
#: config/sweeps): the files in it may name each other
CONFIG_TREE = "config"


def fence_root(folder: str | os.PathLike[str]) -> Path:
    """Where the files a file in ``folder`` names must lie: the nearest
    enclosing folder named :data:`CONFIG_TREE` (an experiment in
    ``config/experiments/robust/`` names ``config/plants/…``, a sweep in
    ``config/sweeps/`` names ``config/experiments/…``), else ``folder``
    itself; resolved (symlinks followed, as the paths it is compared with)."""
    here = Path(os.path.abspath(folder)).resolve()
    for d in (here, *here.parents):
        if d.name == CONFIG_TREE:
            return d
    return here


@dataclass(frozen=True)
class Fence:
    """Where the files a config names may lie (the D16 rule, for every path
    a config, sweep, dataset description or sidecar names).

    ``root`` (resolved) is the folder they must lie under, None for anywhere
    (``--allow-outside-paths``); ``allowed`` are files named on the command
    line (``simulate --replay RUN.csv``), which may lie anywhere; ``where``
    and ``hint`` word the refusal."""

    root: Path | None
    allowed: frozenset[Path] = frozenset()
    where: str = "the config's folder"
    hint: str = "move it there or pass --allow-outside-paths"
    #: every file it admitted (the command's inputs, which no output may replace: :func:`refuse_inputs`)
    admitted: list[Path] = field(default_factory=list, compare=False, repr=False)

    @classmethod
    def around(cls, folder: str | os.PathLike[str], allow_outside: bool = False,
               allowed: Iterable[str | os.PathLike[str]] = (), what: str = "the config") -> "Fence":
        """The fence of a file in ``folder`` (:func:`fence_root`; None: the
        current directory), or none with ``allow_outside``; ``what`` names
        that file in the refusal."""
        folder = folder if folder is not None else "."
        root = fence_root(folder)
        where = (f"{what}'s folder" if root == Path(os.path.abspath(folder)).resolve()
                 else f"the {CONFIG_TREE}/ tree {what} lies in")
        return cls(None if allow_outside else root, frozenset(Path(a).resolve() for a in allowed), where)

    @classmethod
    def anywhere(cls) -> "Fence":
        return cls(None)

    def to_text(self) -> str | None:
        """The root as plain data (a sweep's task carries it to its worker)."""
        return None if self.root is None else str(self.root)

    @classmethod
    def from_text(cls, root: str | None, where: str = "the sweep's folder") -> "Fence":
        """The fence :meth:`to_text` described."""
        return cls(None if root is None else Path(root), where=where)

    def admit(self, value: Any, base_dir: str | os.PathLike[str], key: str) -> tuple[Path | None, str | None]:
        """The one containment check: ``value`` (a path, relative to
        ``base_dir``) as ``(path, None)`` if it lies under the root (or is
        allowed) and is a regular file, else ``(None, error)``, the error
        naming ``key``. Containment is checked first (symlinks resolved),
        so nothing is said about a file outside but that it is outside;
        a FIFO or a device is "not a regular file", never "no such file".
        The file is not opened."""
        if not isinstance(value, str) or not value:
            return None, f"{key}: must be a file path, got {'an empty string' if value == '' else type(value).__name__}"
        raw = Path(value).expanduser()
        full = raw if raw.is_absolute() else Path(base_dir) / raw
        real = full.resolve()
        if self.root is not None and real not in self.allowed and not real.is_relative_to(self.root):
            return None, (f"{key}: {real} is outside {self.root}, {self.where}, where the files it names must be; "
                          f"{self.hint}")
        kind = not_regular(full)
        if kind == "missing":
            if not full.parent.is_dir():
                return None, f"{key}: no such directory {full.parent} (for {value})"
            return None, f"{key}: no such file: {full}"
        if kind is not None:
            return None, f"{key}: {full}: not a regular file ({kind})"
        self.admitted.append(full)
        return full, None


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


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """``a`` and ``b`` name one file: the same path once resolved, or the
    same inode (a hard link, a symlink)."""
    try:
        if Path(a).resolve() == Path(b).resolve():
            return True
        return os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b)
    except (OSError, RuntimeError):
        return False


def refuse_special(outputs: Iterable[str | os.PathLike[str]], what: str = "--out") -> None:
    """``BadInput`` if an output's name holds something other than a regular
    file or a symlink: ``--force`` replaces a file (or a link, never what it
    points at), never a device, FIFO, socket or directory (as root,
    ``--out /dev/null --force`` would otherwise replace /dev/null).
    Touches nothing."""
    for o in outputs:
        try:
            mode = os.lstat(o).st_mode
        except FileNotFoundError:
            continue
        except OSError as exc:
            raise BadInput(f"{o}: {what}: cannot look at it: {exc.strerror or exc}") from None
        if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
            raise BadInput(f"{o}: {what} names {_kind(mode)}, not a regular file; an output is a file, and --force "
                           "replaces a file, never a device, FIFO, socket or directory")


def refuse_inputs(outputs: Iterable[str | os.PathLike[str]], inputs: Iterable[str | os.PathLike[str]],
                  what: str = "--out") -> None:
    """The one check that an output never replaces an input of its command,
    ``--force`` or not (by name, through a symlink or a hard link):
    ``BadInput`` naming both. Touches nothing."""
    ins = [Path(i) for i in inputs]
    for o in outputs:
        for i in ins:
            if same_file(o, i):
                raise BadInput(f"{o}: {what} would overwrite {i}, an input of this command; refusing, --force or "
                               "not (choose another name)")


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

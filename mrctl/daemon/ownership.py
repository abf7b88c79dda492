"""One device, one daemon: an exclusive lock per device, taken before the link opens.

Two ``mrctl run`` driving one damper fight over its current (seen: 254 link
errors and 2 faults in the first one). So the service takes a lock keyed on
the device's identity (:meth:`Link.device_key`: the serial port's real
path, or ``host:port`` and unit of a network device, resolved) before it
opens the link; a second daemon is refused before it sends anything, with a
message naming the device and the owner's pid (exit 3). Serial ports are
also opened with pyserial's ``exclusive=True`` (``flock`` on the port), which
holds against other programs that ask for it too.

The lock is ``fcntl.flock(LOCK_EX | LOCK_NB)`` on a file ``<key>.lock``:
the kernel drops it when its holder exits, however it exits (SIGKILL
included), so a stale file never blocks a start. The file holds the owner's
pid, key and command; the busy message takes the pid from ``/proc/locks``
(the lock's true holder) and falls back to the file. The holder unlinks
the file on release while still holding it; a taker checks, once locked,
that the path still names the file it locked (else it retries), so an
unlink can never let two holders in.

Where the lock files live (:func:`lock_dir`), so that every user's daemon
sees every other's:

1. ``$MRCTL_LOCK_DIR`` if set;
2. ``/run/lock/mrctl``, shared by all users: created 1777 (sticky, like
   ``/tmp``: anyone may lock, nobody may remove another's file) if missing;
   the systemd units need ``systemd/mrctl-tmpfiles.conf`` installed
   (docs/install.md) because ``ProtectSystem=strict`` makes ``/run/lock``
   read-only to them. Not used if it is a symlink, or world-writable
   without the sticky bit;
3. else the per-user directory (``$TMPDIR/mrctl-<uid>``, 0700), with a
   warning: then only this user's daemons see the lock (pyserial's
   exclusive open still protects serial ports from everyone).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import stat
from pathlib import Path
from typing import Any, Callable, Mapping

from mrctl.errors import LinkFailure
from mrctl.util.files import flock_holder, per_user_dir, private_dir

__all__ = ["DeviceBusy", "DeviceLock", "acquire", "own", "lock_dir", "SHARED_LOCK_BASE"]

SHARED_LOCK_BASE = Path("/run/lock")


class DeviceBusy(LinkFailure):
    """The device is owned by another running mrctl (exit 3)."""


def lock_dir(base: Path = SHARED_LOCK_BASE, env: Mapping[str, str] = os.environ,
             fallback: Path | None = None) -> tuple[Path, bool]:
    """(the directory for lock files, whether all users share it); see the module doc."""
    explicit = env.get("MRCTL_LOCK_DIR")
    if explicit:
        d = Path(explicit)
        d.mkdir(parents=True, exist_ok=True)
        return d, True
    d = Path(base) / "mrctl"
    try:
        if not os.path.lexists(d):
            try:
                os.mkdir(d, 0o1777)
                os.chmod(d, 0o1777)  # the umask took the others' bits
            except FileExistsError:
                pass
        st = os.lstat(d)
        mode = st.st_mode
        if (stat.S_ISDIR(mode) and (not mode & 0o002 or mode & stat.S_ISVTX)
                and os.access(d, os.W_OK | os.X_OK)):
            return d, True
    except OSError:
        pass
    return private_dir(fallback or per_user_dir()), False


_default_lock_dir = lock_dir  # acquire() has a parameter of that name


def _file_name(key: str) -> str:
    readable = re.sub(r"[^A-Za-z0-9.:_-]+", "_", key).strip("_")[:80]
    return f"{readable}-{hashlib.sha256(key.encode()).hexdigest()[:12]}.lock"


class DeviceLock:
    """A held device lock; :meth:`release` (idempotent) lets it go."""

    def __init__(self, key: str, path: Path, fd: int, shared: bool) -> None:
        self.key = key
        self.path = path
        self.shared = shared
        self._fd: int | None = fd

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if os.fstat(fd).st_ino == os.stat(self.path, follow_symlinks=False).st_ino:
                os.unlink(self.path)  # still holding it: no one can be between open and lock
        except OSError:
            pass  # another user's file in a sticky directory: it stays, unlocked
        os.close(fd)

    def __enter__(self) -> "DeviceLock":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


#: the mode mrctl gives a lock file it creates
LOCK_MODE = 0o644


def _refuse(path: Path, st: os.stat_result, why: str) -> OSError:
    return OSError(f"{path} {why} (owner uid {st.st_uid}, mode {stat.S_IMODE(st.st_mode):04o}): not a lock file "
                   f"mrctl made, perhaps planted by another user; refusing to start (ask its owner or root to "
                   f"remove it)")


def _check_lock_file(path: Path, st: os.stat_result) -> None:
    """A lock file must be a regular file, and one mrctl made: ours, root's,
    or another user's daemon's (mode 0644, as :func:`_open` creates them)."""
    if not stat.S_ISREG(st.st_mode):
        raise _refuse(path, st, f"is {_kind(st.st_mode)}, not a regular file")
    if st.st_uid not in (os.getuid(), 0) and stat.S_IMODE(st.st_mode) != LOCK_MODE:
        raise _refuse(path, st, f"is another user's file not of mode {LOCK_MODE:04o}")


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory"),
                       (stat.S_ISLNK, "a symlink")):
        if test(mode):
            return name
    return "not a regular file"


def _open(path: Path) -> int:
    """Open (or create) the lock file without following a symlink and
    without blocking (O_NONBLOCK: a FIFO planted at the path would block an
    open for read forever), and check it (:func:`_check_lock_file`). O_CREAT
    only when it is missing: fs.protected_regular refuses O_CREAT on another
    user's file in a sticky directory. Read-only if we may not write it
    (flock works on any descriptor)."""
    nf = os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK
    for _ in range(10):
        for flags in (os.O_RDWR, os.O_RDONLY):
            try:
                fd = os.open(path, flags | nf)
            except PermissionError:
                continue
            except FileNotFoundError:
                break
            except OSError as exc:  # ELOOP: a symlink; ENXIO: a FIFO or socket nobody serves
                try:
                    st = os.lstat(path)
                except OSError:
                    raise OSError(f"{path}: cannot open it: {exc.strerror or exc}") from None
                raise _refuse(path, st, f"is {_kind(st.st_mode)}, not a regular file") from None
            try:
                _check_lock_file(path, os.fstat(fd))
            except OSError:
                os.close(fd)
                raise
            return fd
        else:
            try:
                st = os.lstat(path)
            except OSError as exc:
                raise OSError(f"{path}: cannot open it: {exc.strerror or exc}") from None
            _check_lock_file(path, st)
            raise _refuse(path, st, "cannot be opened by this user (uid %d)" % os.getuid())
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | nf, LOCK_MODE)
            os.fchmod(fd, LOCK_MODE)
            return fd
        except FileExistsError:
            continue  # created meanwhile: open that one
    raise OSError(f"{path}: keeps appearing and vanishing")


def _holder_pid(path: Path, fd: int) -> int | None:
    """The pid holding the flock on this file (/proc/locks), else the file's first line."""
    pid = flock_holder(fd)
    if pid is not None:
        return pid
    try:
        first = os.pread(fd, 64, 0).split(b"\n", 1)[0]
        return int(first) if first.strip().isdigit() else None
    except OSError:
        return None


def _note(fd: int) -> str:
    try:
        lines = os.pread(fd, 4096, 0).decode("utf-8", "replace").splitlines()
    except OSError:
        return ""
    return lines[2].strip() if len(lines) > 2 else ""


def acquire(key: str, note: str = "", lock_dir: Path | None = None) -> DeviceLock:
    """Take the lock of device ``key`` for this process, or raise
    :class:`DeviceBusy` naming the device and the owner's pid. ``note``
    (e.g. the command and config) is written into the lock file for others
    to read. ``lock_dir`` overrides :func:`lock_dir`."""
    if lock_dir is not None:
        d, shared = Path(lock_dir), True
        d.mkdir(parents=True, exist_ok=True)
    else:
        d, shared = _default_lock_dir()
    path = d / _file_name(key)
    for _ in range(10):
        try:
            fd = _open(path)
        except OSError as exc:
            raise LinkFailure(f"device {key}: cannot take its lock: {exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid, who = _holder_pid(path, fd), _note(fd)
            os.close(fd)
            owner = f"pid {pid}" if pid else "a process that did not record its pid"
            raise DeviceBusy(f"device {key} is in use by another mrctl ({owner}{': ' + who if who else ''}); "
                             f"refusing to start: nothing was sent to it (lock {path})") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path, follow_symlinks=False).st_ino
        except FileNotFoundError:
            same = False
        if not same:  # its owner unlinked it between our open and our lock: take the new one
            os.close(fd)
            continue
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n{key}\n{note}\n".encode(), 0)
        except OSError:
            pass  # a file another user created: locked all the same (/proc/locks names us)
        return DeviceLock(key, path, fd, shared)
    raise LinkFailure(f"device {key}: could not take its lock {path} (it keeps changing)")


def device_key_of(link: Any) -> str | None:
    """The device ``link`` is for (:meth:`Link.device_key`), None for one
    nothing else can reach (the in-process bench); every Link has the
    method, a test's stand-in may not."""
    key_of = getattr(link, "device_key", None)
    return key_of() if key_of is not None else None


def own(link: Any, note: str, warn: Callable[[str], None]) -> DeviceLock | None:
    """The service's step: lock the device ``link`` is for (None: a device
    nothing else can reach, e.g. the in-process bench). :class:`DeviceBusy`
    names the device as the user gave it, too; a per-user lock is warned about."""
    key = device_key_of(link)
    if not key:
        return None
    try:
        lock = acquire(key, note)
    except DeviceBusy as exc:
        raise DeviceBusy(f"{link.describe().split(',')[0]}: {exc}") from None
    if not lock.shared:
        warn(f"device lock {lock.path} is seen by this user's mrctl only "
             f"(/run/lock/mrctl is not usable here; docs/install.md)")
    return lock

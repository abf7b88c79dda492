"""The device end of a serial line: a pty whose host-side tty is symlinked at ``--link``.

:class:`PtyEndpoint` creates a pseudo-terminal pair and publishes the
*host-side* tty (the slave, e.g. ``/dev/pts/7``) as a symlink at the
``--link`` path, so the host opens it like a real port
(``serial_for_url('/tmp/mrctl-sim-tty')``). The device side is the master
fd. The process keeps the slave fd open itself, so the host may close and
reopen the port without the master seeing EIO. Both serial transports use
it: the framed protocol (:mod:`hil_sim.serial_device`) and Modbus RTU
(:mod:`hil_sim.modbus_rtu`); the ``disconnect`` fault hangs it up.
"""

from __future__ import annotations

import os
import stat
import tty
from pathlib import Path

__all__ = ["LinkPathError", "PtyEndpoint"]


class LinkPathError(Exception):
    """The ``--link`` path can't be used (a regular file, missing directory...)."""


class PtyEndpoint:
    """A pty pair whose host-side tty is symlinked at ``link_path``.

    An existing symlink at ``link_path`` is replaced (atomically); anything
    else there (a regular file, a directory) is refused. :meth:`close`
    removes the symlink if it still points at this pty, and closes both fds.
    """

    def __init__(self, link_path: str | os.PathLike[str]) -> None:
        self.link = Path(link_path)
        try:
            st = os.lstat(self.link)
        except FileNotFoundError:
            st = None
        except OSError as e:
            raise LinkPathError(f"link path {self.link}: {e.strerror}") from None
        if st is not None and not stat.S_ISLNK(st.st_mode):
            kind = ("a regular file" if stat.S_ISREG(st.st_mode)
                    else "a directory" if stat.S_ISDIR(st.st_mode) else "not a symlink")
            raise LinkPathError(f"link path {self.link} is {kind}; refusing to replace it "
                                "(remove it or choose another --link)")
        if not self.link.parent.is_dir():
            raise LinkPathError(f"link path {self.link}: directory {self.link.parent} does not exist")
        self.master_fd = self.slave_fd = -1
        self._linked = False
        self.tty_path = ""
        self.hangups = 0
        self._open()

    def _open(self) -> None:
        self.master_fd, self.slave_fd = os.openpty()
        try:
            tty.setraw(self.slave_fd)  # no echo / CR-LF mangling before the host configures it
            self.tty_path = os.ttyname(self.slave_fd)
            tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            os.symlink(self.tty_path, tmp)
            os.replace(tmp, self.link)
            self._linked = True
            os.set_blocking(self.master_fd, False)
        except OSError as e:
            self._close_fds()
            raise LinkPathError(f"link path {self.link}: cannot create symlink: {e.strerror}") from None

    @property
    def is_open(self) -> bool:
        return self.master_fd >= 0

    def hangup(self) -> None:
        """The ``disconnect`` fault: remove the symlink and close both ends of the
        pty, as if the USB-serial adapter were unplugged. The host's open port
        then fails every read/write with EIO (pyserial: ``SerialException`` →
        mrctl ``Disconnected``) and reopening the link path fails (no such file)
        until :meth:`reopen`."""
        self._unlink()
        if self.master_fd >= 0:
            self._close_fds()
        self.hangups += 1

    def reopen(self) -> None:
        """After :meth:`hangup`: a new pty (a new ``/dev/pts/N``) at the same link path."""
        if self.master_fd < 0:
            self._open()

    def _close_fds(self) -> None:
        for fd in (self.master_fd, self.slave_fd):
            try:
                os.close(fd)
            except OSError:
                pass
        self.master_fd = self.slave_fd = -1

    def _unlink(self) -> None:
        if self._linked:
            self._linked = False
            try:
                if os.readlink(self.link) == self.tty_path:
                    os.unlink(self.link)
            except OSError:
                pass

    def close(self) -> None:
        """Remove the symlink (if still ours) and close the pty. Idempotent."""
        self._unlink()
        if self.master_fd >= 0:
            self._close_fds()

    def __enter__(self) -> "PtyEndpoint":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

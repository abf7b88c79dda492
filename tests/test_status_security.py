"""The status socket without systemd: a private directory, not trusted when it is
not ours; ``mrctl status`` never crashes on a reply it did not expect."""

from __future__ import annotations

import os
import socket
import stat
import tempfile
import threading
from pathlib import Path

import pytest

from mrctl.cli import main


@pytest.fixture
def private_tmp(tmp_path, monkeypatch):
    """The per-user fallback directory lives under this test's temp dir, not /tmp."""
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    from mrctl.daemon.status import default_status_socket

    path = Path(default_status_socket())
    assert path.parent == tmp_path / f"mrctl-{os.getuid()}", path  # never the shared /tmp in a test
    return path


class Rogue:
    """Serves ``payload`` to every connection on ``path``."""

    def __init__(self, path: Path, payload: bytes) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.bind(str(path))
        self.sock.listen(4)
        self.sock.settimeout(0.1)
        self.payload = payload
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True)
        self._th.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            with conn:
                conn.sendall(self.payload)

    def close(self) -> None:
        self._stop.set()
        self._th.join(2)
        self.sock.close()


def test_fallback_status_directory_is_created_private(private_tmp):
    from mrctl.daemon.status import StatusServer

    srv = StatusServer(str(private_tmp), lambda: {"pid": 1})
    srv.start()
    try:
        st = private_tmp.parent.stat()
        assert stat.S_IMODE(st.st_mode) == 0o700 and st.st_uid == os.getuid()
    finally:
        srv.close()


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to create a directory owned by another user")
def test_status_directory_planted_by_another_user_is_refused(private_tmp, capsys):
    from mrctl.daemon.status import StatusServer

    d = private_tmp.parent
    d.mkdir()
    os.chmod(d, 0o777)
    os.chown(d, 65534, 65534)  # nobody got there first
    rogue = Rogue(private_tmp, b'{"experiment": "SPOOFED", "pid": 4242, "current_A": 0.0}\n')
    try:
        assert main(["status"]) != 0
        cap = capsys.readouterr()
        assert "SPOOFED" not in cap.out
        assert str(d) in cap.err and "65534" in cap.err
        with pytest.raises(OSError, match="65534"):
            StatusServer(str(private_tmp), lambda: {}).start()
    finally:
        rogue.close()


def test_status_directory_writable_by_others_is_refused(private_tmp, capsys):
    d = private_tmp.parent
    d.mkdir()
    os.chmod(d, 0o777)
    rogue = Rogue(private_tmp, b'{"experiment": "SPOOFED"}\n')
    try:
        assert main(["status"]) != 0
        cap = capsys.readouterr()
        assert "SPOOFED" not in cap.out and "writable" in cap.err
    finally:
        rogue.close()


@pytest.mark.parametrize("payload", [b"[1, 2, 3]\n", b'"hello"\n', b"not json at all\n", b"", b"\xff\xfe\n",
                                     b'{"uptime_s": "soon", "current_A": null, "timing": [1], "pid": {}}\n'])
def test_status_reply_it_did_not_expect_is_a_clean_error(tmp_path, capsys, payload):
    p = tmp_path / "s.sock"
    rogue = Rogue(p, payload)
    try:
        code = main(["status", "--socket", str(p)])
    finally:
        rogue.close()
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err and "internal error" not in cap.err
    if payload.startswith(b"{"):
        assert code == 0 and "soon" in cap.out  # a dict: shown as it is, whatever the types
    else:
        assert code == 3 and "not a status reply" in cap.err

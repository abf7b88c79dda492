"""One device, one daemon: a second ``mrctl run`` on a device in use is refused
before it sends anything (exit 3, naming the device and the owner's pid)."""

from __future__ import annotations

import io
import os
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from fake_devices import Listener

from hil_sim.testing.peers import free_port
from mrctl.daemon.service import RunOptions, Service

ROOT = Path(__file__).resolve().parents[1]
TCP_EXP = (ROOT / "config" / "experiments" / "hil_modbus_tcp.yaml").read_text()


def _holder(key: str, lock_dir: Path) -> subprocess.Popen:
    """Another process owning ``key`` the way a running daemon does."""
    code = textwrap.dedent(f"""
        import sys
        from mrctl.daemon.ownership import acquire
        lock = acquire({key!r}, "a test owner")
        print("held", flush=True)
        sys.stdin.read()
        lock.release()
    """)
    p = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         text=True, env=dict(os.environ, MRCTL_LOCK_DIR=str(lock_dir),
                                             PYTHONPATH=str(ROOT)))
    assert p.stdout.readline().strip() == "held"
    return p


def test_refused_daemon_sends_nothing_to_the_device(tmp_path, monkeypatch):
    from mrctl.config import load_experiment
    from mrctl.experiment import build

    monkeypatch.setenv("MRCTL_LOCK_DIR", str(tmp_path / "locks"))
    dev = Listener()
    try:
        cfg = tmp_path / "exp.yaml"
        cfg.write_text(TCP_EXP.replace("port: 5020", f"port: {dev.port}"))
        key = build(load_experiment(cfg)).make_link().device_key()
        assert key is not None and str(dev.port) in key
        owner = _holder(key, tmp_path / "locks")
        try:
            err = io.StringIO()
            out = tmp_path / "run.csv"
            code = Service(RunOptions(str(cfg), out=str(out), duration_s=1.0, live=False, err=err,
                                      stream=io.StringIO(), status_socket=str(tmp_path / "s.sock"))).run()
            msg = err.getvalue()
            assert code == 3, msg
            assert f"pid {owner.pid}" in msg and f"127.0.0.1:{dev.port}" in msg
            assert dev.connections == 0 and dev.bytes == 0  # not even a connect
            assert not out.exists() and not out.with_suffix(".json").exists()
        finally:
            owner.communicate("", timeout=10)
        # the owner is gone: its lock goes with it
        from mrctl.daemon.ownership import acquire

        acquire(key, "test").release()
    finally:
        dev.close()


def test_lock_is_released_on_every_exit(tmp_path, monkeypatch):
    """A start that fails after taking the lock (nothing listens) releases it."""
    from mrctl.daemon.ownership import acquire

    monkeypatch.setenv("MRCTL_LOCK_DIR", str(tmp_path / "locks"))
    port = free_port()  # a port nobody listens on
    cfg = tmp_path / "exp.yaml"
    cfg.write_text(TCP_EXP.replace("port: 5020", f"port: {port}"))
    err = io.StringIO()
    code = Service(RunOptions(str(cfg), out=None, duration_s=1.0, live=False, err=err, stream=io.StringIO(),
                              status_socket=str(tmp_path / "s.sock"))).run()
    assert code == 3 and "cannot open" in err.getvalue()
    acquire(f"tcp local:{port}", "test").release()  # free again


def test_owner_pid_is_in_the_lock_and_a_dead_owner_does_not_block(tmp_path):
    from mrctl.daemon.ownership import DeviceBusy, acquire

    d = tmp_path / "locks"
    lock = acquire("serial /dev/ttyUSB7", "test", lock_dir=d)
    try:
        assert str(os.getpid()) in lock.path.read_text()
        with pytest.raises(DeviceBusy) as ei:
            acquire("serial /dev/ttyUSB7", "test", lock_dir=d)
        assert f"pid {os.getpid()}" in str(ei.value) and "/dev/ttyUSB7" in str(ei.value)
        assert ei.value.exit_code == 3
    finally:
        lock.release()
    # a lock file left by a SIGKILLed owner holds no lock: it is taken over
    path = lock.path
    path.write_text("999999999\nserial /dev/ttyUSB7\n")
    again = acquire("serial /dev/ttyUSB7", "test", lock_dir=d)
    try:
        assert str(os.getpid()) in again.path.read_text()
    finally:
        again.release()


def test_shared_lock_dir_is_sticky_and_world_writable_and_a_foreign_one_is_not_trusted(tmp_path, capsys):
    from mrctl.daemon.ownership import lock_dir

    base = tmp_path / "run_lock"
    base.mkdir()
    d, shared = lock_dir(base=base, env={})
    assert shared and d == base / "mrctl"
    mode = stat.S_IMODE(d.stat().st_mode)
    assert mode == 0o1777  # every user's daemon can lock, none can remove another's file
    if os.geteuid() == 0:
        # planted by another user without the sticky bit: not trusted; per-user fallback
        evil = tmp_path / "evil"
        (evil / "mrctl").mkdir(parents=True)
        os.chmod(evil / "mrctl", 0o777)
        os.chown(evil / "mrctl", 65534, 65534)
        d2, shared2 = lock_dir(base=evil, env={}, fallback=tmp_path / "mine")
        assert not shared2 and d2 == tmp_path / "mine"


def test_links_give_stable_device_keys(tmp_path):
    from mrctl.io.modbus import ModbusLink
    from mrctl.io.serial import SerialLink

    real = tmp_path / "ttyUSB0"
    real.touch()
    alias = tmp_path / "by-id"
    alias.symlink_to(real)
    assert SerialLink(str(alias)).device_key() == SerialLink(str(real)).device_key() == f"serial {real}"
    assert SerialLink("socket://localhost:7000").device_key() == "tcp local:7000"
    assert SerialLink("loop://").device_key() is None
    assert ModbusLink("tcp", host="localhost", port=502, unit_id=3, gateway=True).device_key() == "tcp local:502 unit 3"
    assert ModbusLink("tcp", host="127.0.0.1", port=502, unit_id=4, gateway=True).device_key() == "tcp local:502 unit 4"
    assert ModbusLink("tcp", host="192.0.2.7", port=502).device_key() == "tcp 192.0.2.7:502"
    assert ModbusLink("rtu", url=str(alias)).device_key() == f"serial {real}"


def test_a_tcp_device_is_its_endpoint_whatever_the_unit_id_or_spelling():
    """D1: unit id 0 (which a direct device and hil_sim answer) or an
    IPv4-mapped IPv6 spelling took another lock, and a second daemon drove
    the owner's device. One endpoint is one device unless it is a gateway."""
    from mrctl.io.modbus import ModbusLink
    from mrctl.io.serial import SerialLink

    keys = {ModbusLink("tcp", host=h, port=5020, unit_id=u).device_key()
            for h in ("127.0.0.1", "localhost", "::ffff:127.0.0.1", "[::ffff:127.0.0.1]", "::FFFF:7f00:1")
            for u in (0, 1, 17, 247)}
    keys.add(SerialLink("socket://127.0.0.1:5020").device_key())
    assert keys == {"tcp local:5020"}
    assert ModbusLink("tcp", host="::1", port=502).device_key() == "tcp local:502"
    assert ModbusLink("tcp", host="0:0:0:0:0:0:0:1", port=502).device_key() == "tcp local:502"
    gw = {ModbusLink("tcp", host="::ffff:127.0.0.1", port=502, unit_id=u, gateway=True).device_key() for u in (0, 1)}
    assert gw == {"tcp local:502 unit 0", "tcp local:502 unit 1"}
    assert ModbusLink("tcp", host="2001:db8::5", port=502).device_key() == "tcp [2001:db8::5]:502"


def test_every_local_spelling_of_a_device_served_on_this_host_is_one_key():
    """A daemon on 0.0.0.0:P was not refused while another owned 127.0.0.1:P (both wrote
    DAC0 for 3 s): the unspecified, loopback and this host's own interface addresses, and
    its name, all reach one device served here."""
    import socket

    from mrctl.io.device_keys import _local_addresses, network_device_key

    spellings = ["0.0.0.0", "::", "[::]", "localhost", "127.0.0.1", "127.3.2.1", "::1", "::ffff:127.0.0.1",
                 socket.gethostname(), *sorted(_local_addresses())]
    assert {network_device_key("modbus-tcp", h, 5021) for h in spellings} == {"tcp local:5021"}
    assert network_device_key("modbus-tcp", "0.0.0.0", 5021, unit=2) == "tcp local:5021 unit 2"
    assert network_device_key("modbus-tcp", "0.0.0.0", 5022) != network_device_key("modbus-tcp", "::", 5021)


def test_the_config_says_gateway(tmp_path):
    from mrctl.config import load_experiment
    from mrctl.experiment import build

    cfg = tmp_path / "exp.yaml"
    cfg.write_text(TCP_EXP.replace("unit_id: 1", "unit_id: 0"))
    assert build(load_experiment(cfg)).make_link().device_key() == "tcp local:5020"
    cfg.write_text(TCP_EXP.replace("unit_id: 1", "unit_id: 0, gateway: true"))
    assert build(load_experiment(cfg)).make_link().device_key() == "tcp local:5020 unit 0"


def test_serial_ports_are_opened_exclusively():
    from mrctl.io.base import Disconnected
    from mrctl.io.modbus import ModbusLink
    from mrctl.io.serial import SerialLink

    master, slave = os.openpty()
    name = os.ttyname(slave)
    try:
        a = SerialLink(name, safe_on_close=False)
        a.open()
        try:
            with pytest.raises(Disconnected):
                SerialLink(name, safe_on_close=False).open()
            with pytest.raises(Disconnected):
                ModbusLink("rtu", url=name, use_fc23=True, safe_on_close=False).open()
        finally:
            a.close()
        b = SerialLink(name, safe_on_close=False)
        b.open()  # free again once closed
        b.close()
    finally:
        os.close(slave)
        os.close(master)


# -- two real daemons against hil_sim -------------------------------------------------
@pytest.mark.hil
@pytest.mark.parametrize("transport", ["modbus-tcp", "serial"])
def test_second_daemon_on_a_device_in_use_is_refused_naming_the_owner(tmp_path, transport):
    from hil_sim.testing.daemon_faults import ownership

    r = ownership(transport, tmp_path, lock_dir=tmp_path / "locks")
    assert r["a_in_loop"], f"the first daemon did not reach its loop: {r['a_messages']}"
    assert r["b_exit"] == 3, r
    assert r["b_names_owner_pid"] and r["b_names_device"], r["b_messages"]
    assert not r["b_wrote_log"]
    # A completed (its verdict may be degraded by two daemons starting beside it on a small machine)
    assert r["a_exit"] in (0, 5), r["a_messages"]


def _as_user(uid: int, fn) -> tuple[int, int, int]:
    """Fork; the child becomes ``uid`` and runs ``fn(wait, say)``: ``wait()``
    blocks until the parent writes to the go pipe, ``say(msg)`` reports a
    line. Returns (child pid, the report pipe to read, the go pipe to write)."""
    r, w = os.pipe()
    r2, w2 = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        try:
            os.close(r)
            os.close(w2)
            os.setgid(uid)
            os.setuid(uid)
            res = fn(lambda: os.read(r2, 1), lambda msg: os.write(w, (msg + "\n").encode()))
        except BaseException as exc:  # noqa: BLE001
            res = f"{type(exc).__name__}: {exc}"
        os.write(w, (str(res) + "\n").encode())
        os._exit(0)
    os.close(w)
    os.close(r2)
    return pid, r, w2


def _line(fd: int) -> str:
    out = b""
    while not out.endswith(b"\n"):
        b = os.read(fd, 1)
        if not b:
            break
        out += b
    return out.decode().strip()


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to act as two users")
def test_the_lock_is_seen_across_users(tmp_path):
    """Root's daemon and another user's daemon see each other's locks in the
    shared directory (1777), whoever created the lock file."""
    import tempfile

    from mrctl.daemon.ownership import DeviceBusy, acquire, lock_dir

    base = Path(tempfile.mkdtemp(dir="/tmp", prefix="mrctl-locktest-"))
    try:
        os.chmod(base, 0o755)
        d, shared = lock_dir(base=base, env={})
        assert shared
        key = "serial /dev/ttyUSB9"

        def try_once(wait, say):
            try:
                acquire(key, "nobody's daemon", lock_dir=d).release()
                return "acquired"
            except DeviceBusy as exc:
                return f"busy: {exc}"

        # 1. root holds it: the other user is refused, told root's pid
        mine = acquire(key, "root's daemon", lock_dir=d)
        pid, r, w = _as_user(65534, try_once)
        got = _line(r)
        os.waitpid(pid, 0)
        assert got.startswith("busy:") and f"pid {os.getpid()}" in got, got
        mine.release()

        # 2. the other user holds it (its own file, or root's left behind): root is refused, told its pid
        for leftover in (False, True):
            if leftover:  # a file root created and left (a SIGKILLed owner): the other user can only read it
                held = acquire(key, "root", lock_dir=d)
                os.close(held._fd)  # killed: the lock goes, the file stays
                held._fd = None

            def hold(wait, say):
                lock = acquire(key, "nobody's daemon", lock_dir=d)
                say("held")
                wait()
                lock.release()
                return "released"

            pid, r, w = _as_user(65534, hold)
            assert _line(r) == "held"
            with pytest.raises(DeviceBusy, match=f"pid {pid}"):
                acquire(key, "root again", lock_dir=d)
            os.write(w, b"x")
            assert _line(r) == "released"
            os.waitpid(pid, 0)
            acquire(key, "root", lock_dir=d).release()  # free again
    finally:
        import shutil

        shutil.rmtree(base, ignore_errors=True)


def test_a_fifo_planted_at_the_lock_path_is_refused_not_waited_on(tmp_path, monkeypatch):
    """D20: open() of a FIFO for reading blocked every later start forever.
    Another user's 0444 FIFO: opening it read-write is denied (simulated,
    so that the test means the same as root), read-only it blocks unless
    O_NONBLOCK."""
    import threading

    from mrctl.daemon import ownership
    from mrctl.errors import LinkFailure

    d = tmp_path / "locks"
    d.mkdir()
    key = "tcp local:5020"
    fifo = d / ownership._file_name(key)
    os.mkfifo(fifo, 0o444)
    real_open = os.open

    def as_another_user(path, flags, *a):
        if Path(path) == fifo and flags & os.O_ACCMODE != os.O_RDONLY:
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, flags, *a)

    monkeypatch.setattr(ownership.os, "open", as_another_user)
    box: dict = {}

    def take():
        try:
            ownership.acquire(key, "x", lock_dir=d).release()
        except Exception as exc:  # noqa: BLE001
            box["exc"] = exc

    t = threading.Thread(target=take, daemon=True)
    t.start()
    t.join(5.0)
    if t.is_alive():  # the old code: blocked in open(); let it go before failing
        fd = real_open(fifo, os.O_RDWR | os.O_NONBLOCK)
        t.join(2.0)
        os.close(fd)
        pytest.fail("acquire() blocked on a FIFO at the lock path")
    assert isinstance(box.get("exc"), LinkFailure), box
    msg = str(box["exc"])
    assert "is a FIFO, not a regular file" in msg and "not a lock file mrctl made" in msg


def test_a_planted_unreadable_lock_file_is_refused_with_a_clear_message(tmp_path):
    from mrctl.daemon.ownership import _file_name, acquire
    from mrctl.errors import LinkFailure

    d = tmp_path / "locks"
    d.mkdir()
    key = "serial /dev/ttyUSB9"
    p = d / _file_name(key)
    p.touch()
    os.chmod(p, 0)
    if os.getuid() == 0:
        os.chown(p, 65534, 65534)  # another user's file: root could open it, its mode gives it away
    with pytest.raises(LinkFailure) as e:
        acquire(key, "x", lock_dir=d)
    msg = str(e.value)
    assert "mode 0000" in msg and "not a lock file mrctl made" in msg and "remove it" in msg
    assert e.value.exit_code == 3

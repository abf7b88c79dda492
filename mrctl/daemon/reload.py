"""SIGHUP's new config, parsed and validated in a child process.

A reload runs beside the 1 kHz loop, in the loop's interpreter: whatever
holds that interpreter (the GIL) delays ticks. Parsing and validating a
file the user (or anyone who can write it) hands over is not bounded by
anything the loop controls: an 860-byte YAML alias bomb froze the loop for
21 s, a 2.6 MB config took a minute. So :func:`validate_in_child` does the
whole check (:func:`~mrctl.config.load_experiment`, then
:func:`~mrctl.experiment.build`: the laws are imported, constructed and
reset, data files read) in a fresh interpreter, limited in time
(:data:`RELOAD_TIMEOUT_S`, then killed) and in memory
(:data:`RELOAD_MEMORY_BYTES`, ``RLIMIT_AS``), at nice 19 (it competes
for a CPU with the loop only when the machine is idle enough to afford it),
its output other than the result thrown away (a plugin that prints cannot fill the journal). The
child hands back the validated config as plain data (a pickled
:class:`~mrctl.util.schema.Node`); the daemon builds the laws from it,
which is then quick, since everything slow or hostile was refused in the
child.

The child sees the daemon's ``sys.path`` (plugins named ``module:Class``
import the same) and its working directory.
"""

from __future__ import annotations

import json
import os
import pickle
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from mrctl.util.schema import ConfigError, Node

__all__ = ["validate_in_child", "RELOAD_TIMEOUT_S", "RELOAD_MEMORY_BYTES"]

#: seconds the child may take (a real config: about 0.5 s, most of it Python's start)
RELOAD_TIMEOUT_S = 10.0
#: address space the child may use (Python, numpy and a config need ~300 MB)
RELOAD_MEMORY_BYTES = 1 << 30
#: the largest reply read back (a validated config pickles to a few kB)
MAX_REPLY_BYTES = 4 << 20


def validate_in_child(path: str | os.PathLike[str], timeout_s: float = RELOAD_TIMEOUT_S,
                      memory_bytes: int = RELOAD_MEMORY_BYTES, *, allow_outside: bool = False) -> Node:
    """The validated experiment config in ``path``, checked in a child
    process; :class:`ConfigError` for a bad file, one that takes longer than
    ``timeout_s`` or more than ``memory_bytes``, or a child that died.
    ``allow_outside`` is the CLI's ``--allow-outside-paths``."""
    src = str(path)
    env = dict(os.environ, MRCTL_RELOAD_SYSPATH=json.dumps(sys.path), OPENBLAS_NUM_THREADS="1",
               OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "mrctl.daemon.reload", str(Path(src).absolute()), str(int(memory_bytes)),
           str(max(1, int(timeout_s) + 1)), "outside" if allow_outside else "inside"]
    try:
        p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                             env=env, close_fds=True, start_new_session=True)
    except OSError as exc:
        raise ConfigError([f"cannot start the process that checks it: {exc.strerror or exc}"], src) from None
    try:
        out, _ = p.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        p.kill()
        p.communicate()
        raise ConfigError([f"checking it took longer than {timeout_s:g} s: refused (a real experiment file "
                           f"is checked in well under a second)"], src) from None
    if p.returncode != 0 or not out or len(out) > MAX_REPLY_BYTES:
        how = (f"was killed by {signal.Signals(-p.returncode).name}" if p.returncode < 0
               else f"exited {p.returncode}")
        raise ConfigError([f"checking it failed: the checking process {how} "
                           f"(more than {memory_bytes / (1 << 20):.0f} MiB, or a plugin that ended it)"], src)
    try:
        kind, payload = pickle.loads(out)  # noqa: S301 - our own child's reply, plain data
    except Exception as exc:  # noqa: BLE001
        raise ConfigError([f"checking it failed: unreadable reply ({type(exc).__name__})"], src) from None
    if kind == "ok" and isinstance(payload, Node):
        return payload
    if kind == "config":
        raise ConfigError(list(payload), src)
    raise ConfigError([str(payload)[:400]], src)


def _child(argv: list[str]) -> int:
    """``python -m mrctl.daemon.reload PATH MEMORY_BYTES CPU_S inside|outside``: one pickled
    ``(kind, payload)`` on stdout; anything else the check prints is dropped."""
    import resource

    reply = os.fdopen(os.dup(1), "wb")
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    path, memory, cpu = argv[0], int(argv[1]), int(argv[2])
    allow_outside = len(argv) > 3 and argv[3] == "outside"
    try:
        os.nice(19)  # a background job: on a busy 2-core box it must not take the loop's CPU
    except OSError:
        pass
    resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 1))
    try:
        sys.path[:] = json.loads(os.environ.get("MRCTL_RELOAD_SYSPATH", "[]")) or sys.path
    except ValueError:
        pass
    result: tuple[str, Any]
    try:
        from mrctl.config import load_experiment
        from mrctl.experiment import build

        node = load_experiment(path, allow_outside=allow_outside)
        build(node)  # the laws import, construct and reset here first
        result = ("ok", node)
    except ConfigError as exc:
        result = ("config", exc.errors)
    except MemoryError:
        result = ("error", f"checking it needs more than {memory / (1 << 20):.0f} MiB: refused")
    except RecursionError:
        result = ("error", "nested too deeply: refused")
    except BaseException as exc:  # noqa: BLE001 - whatever the file or a plugin does, one line back
        result = ("error", f"{type(exc).__name__}: {str(exc)[:300]}")
    try:
        data = pickle.dumps(result)
    except Exception as exc:  # noqa: BLE001 - a plugin's object in the config
        data = pickle.dumps(("error", f"the validated config cannot be handed back: {type(exc).__name__}"))
    reply.write(data)
    reply.flush()
    return 0


if __name__ == "__main__":  # pragma: no cover - run as the child
    os._exit(_child(sys.argv[1:]))

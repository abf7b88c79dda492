"""Threads of the hil_sim process (clock, servers) that report their failure."""

from __future__ import annotations

import sys
import threading

__all__ = ["run_server"]


def run_server(target, name: str, failed: list[str], stop: threading.Event) -> threading.Thread:
    """Run ``target()`` in a daemon thread; an exception is reported, recorded
    in ``failed`` and sets ``stop`` (the process then exits non-zero)."""

    def body() -> None:
        try:
            target()
        except BaseException as e:  # noqa: BLE001 - a server thread must not die silently
            failed.append(f"{name}: {type(e).__name__}: {e}")
            print(f"hil_sim: {name} failed: {type(e).__name__}: {e}", file=sys.stderr, flush=True)
            stop.set()

    t = threading.Thread(target=body, name=f"hil_sim-{name}", daemon=True)
    t.start()
    return t

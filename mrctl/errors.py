"""One error tree: every error mrctl reports to a user carries its exit code.

Why a root with the code on it: the CLI has one handler (``mrctl.cli.main``)
that prints ``mrctl: <message>`` and returns ``exc.exit_code``. A module
that raises decides what kind of failure it is; nothing else maps
exceptions to codes. The codes are README's:

    0 success (also when stopped by a signal)
    1 internal error
    2 bad input (config, dataset, CSV, command line, a missing optional dependency)
    3 link failure (cannot open, infeasible rate, driver lost, device owned)
    4 run log incomplete (rows lost, disk error)
    5 run completed but degraded (an ``acceptance`` bound broken: faults,
      skipped deadlines, gaps, forced 0 A, tracking; the sidecar's verdict)

This module imports nothing of mrctl, so every layer may use it.
"""

from __future__ import annotations

import enum


class ExitCode(enum.IntEnum):
    """Process exit codes of ``mrctl`` (README, docs/design.md)."""

    OK = 0
    FAILURE = 1
    BAD_INPUT = 2
    LINK = 3
    LOG = 4
    DEGRADED = 5
    INTERRUPTED = 130


class MrctlError(Exception):
    """Root of every error shown to a user; ``exit_code`` says how mrctl exits."""

    exit_code: int = ExitCode.FAILURE


class BadInput(MrctlError):
    """Something the user gave is wrong: a config key, a file, a CSV, an option."""

    exit_code = ExitCode.BAD_INPUT


class LinkFailure(MrctlError):
    """The device cannot be used: not reachable, too slow, owned by another process."""

    exit_code = ExitCode.LINK


class LogIncomplete(MrctlError):
    """The run log could not be written completely."""

    exit_code = ExitCode.LOG


class DependencyMissing(BadInput):
    """An optional dependency is not installed; the message names the extra
    to install (``pip install 'mrctl[identify]'``). Exit 2, like any input
    the command cannot work with, whichever command meets it."""

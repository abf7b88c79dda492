"""Message priorities that reach the systemd journal: the ``<N>`` line prefix.

A service's stderr goes to the journal, where every line gets the unit's
``SyslogLevel=`` (info) unless it starts with ``<N>`` (sd-daemon(3), read
because ``SyslogLevelPrefix=`` is on by default). So ``journalctl -u mrctl
-p warning`` shows exactly the lines written here with a priority of 4 or
less. The prefix is written when stderr *is* the journal: ``$JOURNAL_STREAM``
names the device and inode of the stream systemd connected (systemd.exec(5)),
and it must match stderr's own, or when asked for (``mrctl run
--log-priorities``). On a terminal the lines stay as they were.
"""

from __future__ import annotations

import os
from typing import TextIO

EMERG, ALERT, CRIT, ERR, WARNING, NOTICE, INFO, DEBUG = range(8)

__all__ = ["EMERG", "ALERT", "CRIT", "ERR", "WARNING", "NOTICE", "INFO", "DEBUG", "stream_is_journal",
           "prefixed", "Journal"]


def stream_is_journal(stream: TextIO, env: dict[str, str] | None = None) -> bool:
    """True if ``stream``'s file descriptor is the one ``$JOURNAL_STREAM`` names."""
    value = (os.environ if env is None else env).get("JOURNAL_STREAM", "")
    dev, _, ino = value.partition(":")
    if not (dev.isdigit() and ino.isdigit()):
        return False
    try:
        st = os.fstat(stream.fileno())
    except (AttributeError, OSError, ValueError):  # a StringIO, a closed stream
        return False
    return st.st_dev == int(dev) and st.st_ino == int(ino)


def prefixed(priority: int, text: str) -> str:
    """``text`` with ``<priority>`` before each of its lines (the journal
    splits a message at newlines and reads the prefix of each line)."""
    p = f"<{min(max(int(priority), EMERG), DEBUG)}>"
    return "\n".join(p + line for line in text.split("\n"))


class Journal:
    """Writes ``mrctl: message`` lines to ``err``, with the priority prefix
    when ``prefix`` (None: when ``err`` is the journal)."""

    def __init__(self, err: TextIO, prefix: bool | None = None) -> None:
        self.err = err
        self.prefix = stream_is_journal(err) if prefix is None else bool(prefix)

    def format(self, priority: int, message: str) -> str:
        text = f"mrctl: {message}"
        return prefixed(priority, text) if self.prefix else text

    def log(self, priority: int, message: str) -> None:
        print(self.format(priority, message), file=self.err, flush=True)

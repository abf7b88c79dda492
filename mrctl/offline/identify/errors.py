"""The errors identification raises, each with the exit code ``mrctl identify`` returns.

``IdentificationError`` is bad or insufficient input (exit 2): the message
says, for the user, which file, column, sample or current is wrong and what
the method needs instead. ``DependencyMissing`` is an installation problem
(exit 2): scipy is absent. What is not an error but the user should know
is a warning line; :func:`merge_warnings` folds the lines that say the same
of several records into one.
"""

from __future__ import annotations

from mrctl.errors import BadInput, DependencyMissing

from typing import Iterable

__all__ = ["IdentificationError", "DependencyMissing", "SCIPY_MISSING", "require_scipy", "merge_warnings"]

SCIPY_MISSING = "scipy is needed for identification: pip install 'mrctl[identify]'"


class IdentificationError(BadInput):
    """The runs cannot be identified from; the message says why, for the user."""


def require_scipy() -> None:
    """Import ``scipy.optimize`` now (not inside the first fit's timing);
    DependencyMissing with the install hint if it is not there."""
    try:
        import scipy.optimize  # noqa: F401
    except ImportError:
        raise DependencyMissing(SCIPY_MISSING) from None


def merge_warnings(warnings: Iterable[str], names: Iterable[str]) -> list[str]:
    """One line per distinct message: ``"NAME: text"`` lines whose text is the
    same for several records (15 records decimated alike) become
    ``"text (15 records: a, b, c, …)"``, in the order first seen; other lines
    stay as they are (an identical line repeated is kept once)."""
    known = sorted({str(n) for n in names}, key=len, reverse=True)  # the longest name that prefixes wins
    groups: dict[str, list[str]] = {}
    for w in warnings:
        name, text = "", w
        for n in known:
            if w.startswith(n + ": "):
                name, text = n, w[len(n) + 2:]
                break
        who = groups.setdefault(text, [])
        if name and name not in who:
            who.append(name)
        elif not name and not who:
            who.append("")
    out = []
    for text, who in groups.items():
        named = [n for n in who if n]
        if len(named) <= 1:
            out.append(f"{named[0]}: {text}" if named else text)
        else:
            shown = ", ".join(named[:3]) + (", …" if len(named) > 3 else "")
            out.append(f"{text} ({len(named)} records: {shown})")
    return out

"""The errors identification raises, each with the exit code ``mrctl identify`` returns.

``IdentificationError`` is bad or insufficient input (exit 2): the message
says, for the user, which file, column, sample or current is wrong and what
the method needs instead. ``DependencyMissing`` is an installation problem
(exit 2): scipy is absent.
"""

from __future__ import annotations

from mrctl.errors import BadInput, DependencyMissing

__all__ = ["IdentificationError", "DependencyMissing", "SCIPY_MISSING", "require_scipy"]

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

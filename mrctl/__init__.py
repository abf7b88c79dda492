"""mrctl: real-time control daemon for the Lord RD-1097-01 MR damper."""

from mrctl.build import install_pure_finder as _install_pure_finder

__version__ = "0.1.0"

# MRCTL_PURE_PYTHON=1: the compiled modules load from their sources (mrctl/build.py)
_install_pure_finder()

"""Okabe & Ito's colour-blind-safe palette (2008): the colours of every mrctl figure.

By name (:data:`OKABE_ITO_NAMED`, the run report's marks) and as the
sequence the identification and sweep figures cycle through, black first
(:data:`OKABE_ITO`).
"""

from __future__ import annotations

__all__ = ["OKABE_ITO_NAMED", "OKABE_ITO"]

OKABE_ITO_NAMED = {"black": "#000000", "orange": "#E69F00", "sky": "#56B4E9", "green": "#009E73",
                   "yellow": "#F0E442", "blue": "#0072B2", "vermillion": "#D55E00", "purple": "#CC79A7"}
OKABE_ITO = tuple(OKABE_ITO_NAMED[n] for n in ("black", "orange", "sky", "green", "blue", "vermillion", "purple",
                                                "yellow"))

"""mrctl: real-time control daemon for the Lord RD-1097-01 MR damper."""

__version__ = "0.1.0"

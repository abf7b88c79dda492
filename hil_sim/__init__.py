"""hil_sim: the simulated bench as its own process, behind the real protocols.

It imports the plant from :mod:`mrctl.model` (never the other way round) and
serves it over serial (framed binary protocol), Modbus TCP and Modbus RTU.
"""

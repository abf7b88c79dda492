"""Control laws: demand laws (F_des), inverse and current laws (I).

The API is :mod:`mrctl.laws.base`; the name table is :mod:`mrctl.laws.registry`.
"""

"""Sweeps: one experiment over grids and Monte Carlo draws, local or on Dask (docs/sweeps.md).

``spec`` (the sweep file and its points), ``point`` (one simulation → one
row), ``metrics`` (the figures kept), ``table`` (the resumable results),
``runner`` (local processes or Dask), ``figure`` (``mrctl report`` of a
results table). An offline tool above :mod:`mrctl.offline`: it runs
``mrctl simulate``'s simulation, unchanged, once per point.
"""

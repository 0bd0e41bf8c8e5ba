"""Layer 1, the DEM engine: particle pools, the hashed-grid neighbour search, contact laws,
bonds, breakage and the :class:`~calendaring.engine.simulation.Simulation` that drives them.

The only layer that imports Taichi. It knows nothing of electrodes, run files or sweeps: it
imports only :mod:`calendaring.core`.

See also: :mod:`calendaring.process` (layer 2), ``docs/architecture.md``.
"""

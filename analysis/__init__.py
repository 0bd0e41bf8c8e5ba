"""analysis: sensitivity, trends, microstructure and the paper's comparison studies.

Modules (imported on demand; nothing heavy at package import):

- :mod:`analysis.outputs`: the four key outputs (peak pressure, stress and diameter
  centroids, low-stress ratio) of pressure curves and breakage distributions.
- :mod:`analysis.sensitivity`: Sobol indices with SALib through a generic unit-cube model
  (Ishigami-tested), convergence over N, ensemble spread, given-data cross-check, Fig. 10.
- :mod:`analysis.trends`: one-at-a-time trends (Fig. 11).
- :mod:`analysis.microstructure`: voxel porosity, TauFactor tortuosity and D_eff (Fig. 13).
- :mod:`analysis.render`: pyvista renders of snapshots and bond networks (Figs. 1, 6).
- :mod:`analysis.compare`: R0/R1 and Table 5 PSD studies through ``calendaring run``.
- :mod:`analysis.cli`: the ``analysis`` command.
"""

"""Layer 2, the calendering process built on the engine: the electrode recipe, packings, the
staged run (build, settle, calender, release), its HDF5 run files, pre-flight resource
estimates and the plots of a run.

Imports :mod:`calendaring.core` and :mod:`calendaring.engine` only.

See also: :mod:`calendaring.data` (layer 3), ``docs/architecture.md``.
"""

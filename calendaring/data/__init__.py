"""Layer 3, the data of many runs: the eight-parameter space, designs, sweeps (local or Dask),
run digests and the training datasets the surrogate, calibration and analysis read.

Imports the layers below (:mod:`calendaring.core`, :mod:`calendaring.engine`,
:mod:`calendaring.process`); only :mod:`calendaring.cli` stands above it.

See also: ``docs/architecture.md``.
"""

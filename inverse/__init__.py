"""inverse: infer the eight breakage parameters from a measured pressure-depth curve.

The paper's method (section 2.4) on a trained surrogate (:func:`surrogate.load`), and more:

    >>> import surrogate
    >>> from inverse.targets import load_target
    >>> from inverse.calibrate import calibrate_target
    >>> from inverse.posterior import PosteriorConfig
    >>> from inverse.report import format_table4
    >>> m = surrogate.load("model.pt")
    >>> t = load_target("curve.csv", m)          # depth_um,pressure_MPa[,sigma_MPa] or RUN.h5
    >>> out = calibrate_target(m, t, fix={"damage_constant": 5.549},
    ...                        posterior=PosteriorConfig())
    >>> print(format_table4(out.result))

Modules: :mod:`~inverse.targets` (CSV and run-file targets on the model's depths),
:mod:`~inverse.loss` (weighted Huber + centroid + boundary terms), :mod:`~inverse.optimise`
(Sobol starts, Adam then L-BFGS with projection, restarts, clustering of many optima),
:mod:`~inverse.identifiability` (Hessian spectrum, loss profiles), :mod:`~inverse.posterior`
(emcee with observation and surrogate variance), :mod:`~inverse.calibrate` (one calibration
end to end), :mod:`~inverse.report` (Table 4 layout, result JSON), :mod:`~inverse.verify`
(DEM runs at the result), :mod:`~inverse.validate` (recovery and coverage on held-out runs),
:mod:`~inverse.cli` (``inverse calibrate | verify | validate``).
"""

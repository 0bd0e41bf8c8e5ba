"""PCA + Gaussian-process baseline for the pressure curve (Higdon et al. 2008, JASA 103:570).

The normalised pressure curves of the training rows are reduced to their first
``n_components`` principal components (scikit-learn ``PCA``); each component score gets its
own Gaussian process over the eight unit parameters (scikit-learn
``GaussianProcessRegressor``, constant x anisotropic Matern-5/2 plus white noise, hyper-
parameters by maximum marginal likelihood). Predictions map back through the components;
the variance adds the components' GP variances (scores treated as independent) and ignores
the discarded components.

It is a baseline for the MLP's pressure branch, evaluated on the same splits and folds in
:mod:`surrogate.evaluate`; it does not model the distribution.
"""

from __future__ import annotations

import warnings

import numpy as np
from sklearn.decomposition import PCA
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel
from threadpoolctl import threadpool_limits

from calendaring import ConfigError


class PCAGPBaseline:
    """PCA of the curves, one GP per component score; inputs are unit parameters."""

    def __init__(self, n_components: int = 8, seed: int = 0, n_restarts: int = 0,
                 blas_threads: int | None = 1):
        if int(n_components) < 1:
            raise ConfigError("n_components", n_components, "an integer >= 1")
        self.n_components = int(n_components)
        self.seed = int(seed)
        self.n_restarts = int(n_restarts)
        self.blas_threads = blas_threads  # small matrices: one BLAS thread is fastest
        self.pca: PCA | None = None
        self.gps: list[GaussianProcessRegressor] = []

    def fit(self, u: np.ndarray, y: np.ndarray) -> PCAGPBaseline:
        """Fit on unit parameters ``u (n, d)`` and curves ``y (n, m)`` (normalised units)."""
        with threadpool_limits(self.blas_threads):
            return self._fit(u, y)

    def _fit(self, u: np.ndarray, y: np.ndarray) -> PCAGPBaseline:
        u = np.asarray(u, float)
        y = np.asarray(y, float)
        k = min(self.n_components, len(y) - 1, y.shape[1])
        if k < 1:
            raise ConfigError("baseline rows", len(y), "at least 2 rows")
        self.pca = PCA(n_components=k, random_state=self.seed).fit(y)
        scores = self.pca.transform(y)  # (n, k)
        self.gps = []
        for j in range(k):
            kernel = (ConstantKernel(1.0, (1e-3, 1e3))
                      * Matern(length_scale=np.ones(u.shape[1]), length_scale_bounds=(1e-2, 1e2),
                               nu=2.5)
                      + WhiteKernel(1e-4, (1e-10, 1e-1)))
            gp = GaussianProcessRegressor(kernel, normalize_y=True,
                                          n_restarts_optimizer=self.n_restarts,
                                          random_state=self.seed + j)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                gp.fit(u, scores[:, j])
            self.gps.append(gp)
        return self

    def predict(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean ``(n, m)`` and standard deviation ``(n, m)`` of the curves (normalised units)."""
        if self.pca is None:
            raise RuntimeError("PCAGPBaseline.predict called before fit")
        u = np.atleast_2d(np.asarray(u, float))
        mean_s, var_s = [], []
        with threadpool_limits(self.blas_threads):
            for gp in self.gps:
                m, s = gp.predict(u, return_std=True)
                mean_s.append(m)
                var_s.append(s**2)
        mean_s = np.stack(mean_s, axis=1)  # (n, k)
        var_s = np.stack(var_s, axis=1)
        mean = self.pca.inverse_transform(mean_s)  # (n, m)
        var = var_s @ (self.pca.components_**2)  # (n, m)
        return mean, np.sqrt(var)


__all__ = ["PCAGPBaseline"]

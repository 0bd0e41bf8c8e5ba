"""The PCA + GP pressure branch as a differentiable torch module (``--pressure-head gp``).

:class:`~surrogate.baseline.PCAGPBaseline` (Higdon et al. 2008, JASA 103:570) is fitted with
scikit-learn; :class:`GPPressure` holds what its prediction needs as buffers and evaluates
the posterior in torch, so that calibration (Adam, L-BFGS, the posterior's gradients) runs
through it as through the MLP. For component ``j`` with Matern-5/2 kernel
``k_j(x, x') = s_j (1 + sqrt(5) r + 5 r^2 / 3) exp(-sqrt(5) r)``,
``r = |(x - x') / l_j|``, fitted on ``n`` rows ``X`` with noise (Rasmussen & Williams 2006,
eqs. 2.25-2.26, with scikit-learn's ``normalize_y``):

    mean_j(x) = mu_j + sd_j * k_j(x, X) alpha_j
    var_j(x)  = sd_j^2 * (s_j - k_j(x, X) K_j^-1 k_j(X, x))

``K_j^-1`` enters through the Cholesky factor (a triangular solve, as scikit-learn; an
explicit inverse loses digits where the variance is small). ``var`` is the variance of the
latent mean (the white-noise term is left out: it is the
DEM's run-to-run scatter, not the surrogate's uncertainty about the mean). Curves are
``pca_mean + scores @ components`` in the model's normalised cube-root units; their
variance adds the components' variances (scores independent, as the baseline assumes).
Arithmetic is float64 inside (``K^-1`` of a few hundred rows loses digits in float32); the
outputs take the input's dtype.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch
from torch import nn

from calendaring import ConfigError
from surrogate.baseline import PCAGPBaseline

SQRT5 = math.sqrt(5.0)


def _kernel_parts(gp) -> tuple[float, np.ndarray, float]:
    """(signal variance s, length scales l (d,), noise level) of a fitted
    ``ConstantKernel * Matern(nu=2.5) + WhiteKernel`` (the baseline's kernel)."""
    k = gp.kernel_
    try:
        const, matern, white = k.k1.k1, k.k1.k2, k.k2
        s, ell, noise = float(const.constant_value), matern.length_scale, white.noise_level
    except AttributeError:
        raise ConfigError("GP kernel", str(k),
                          "ConstantKernel * Matern(nu=2.5) + WhiteKernel") from None
    if getattr(matern, "nu", None) != 2.5:
        raise ConfigError("GP kernel nu", getattr(matern, "nu", None), "2.5")
    return s, np.broadcast_to(np.asarray(ell, float), (gp.X_train_.shape[1],)).copy(), \
        float(noise)


class GPPressure(nn.Module):
    """Posterior mean and latent variance of a fitted PCA + GP pressure model.

    Build with :meth:`from_baseline`; ``GPPressure(n_rows, n_inputs, n_components,
    n_pressure)`` makes empty buffers of the right shapes for ``load_state_dict``.
    """

    def __init__(self, n_rows: int, n_inputs: int, n_components: int, n_pressure: int):
        super().__init__()
        for key, v in (("n_rows", n_rows), ("n_inputs", n_inputs),
                       ("n_components", n_components), ("n_pressure", n_pressure)):
            if int(v) < 1:
                raise ConfigError(f"pressure_gp.{key}", v, "an integer >= 1")
        n, d, k, m = int(n_rows), int(n_inputs), int(n_components), int(n_pressure)
        self.shape = {"n_rows": n, "n_inputs": d, "n_components": k, "n_pressure": m}
        f64 = torch.float64
        self.register_buffer("x_train", torch.zeros(n, d, dtype=f64))  # unit parameters
        self.register_buffer("alpha", torch.zeros(k, n, dtype=f64))  # K^-1 y (normalised y)
        self.register_buffer("chol", torch.zeros(k, n, n, dtype=f64))  # K = L L^T, noise incl.
        self.register_buffer("length_scale", torch.ones(k, d, dtype=f64))
        self.register_buffer("signal_var", torch.ones(k, dtype=f64))
        self.register_buffer("noise_var", torch.zeros(k, dtype=f64))  # kept for the record
        self.register_buffer("y_mean", torch.zeros(k, dtype=f64))
        self.register_buffer("y_std", torch.ones(k, dtype=f64))
        self.register_buffer("pca_mean", torch.zeros(m, dtype=f64))
        self.register_buffer("components", torch.zeros(k, m, dtype=f64))

    @classmethod
    def from_baseline(cls, b: PCAGPBaseline) -> GPPressure:
        """Copy a fitted :class:`PCAGPBaseline` (its kernels must be the baseline's)."""
        if b.pca is None or not b.gps:
            raise ConfigError("PCAGPBaseline", "not fitted", "a fitted baseline (call fit)")
        x = np.asarray(b.gps[0].X_train_, float)
        out = cls(len(x), x.shape[1], len(b.gps), b.pca.components_.shape[1])
        with torch.no_grad():
            out.x_train.copy_(torch.as_tensor(x))
            for j, gp in enumerate(b.gps):
                s, ell, noise = _kernel_parts(gp)
                out.alpha[j] = torch.as_tensor(np.asarray(gp.alpha_, float).ravel())
                out.chol[j] = torch.as_tensor(np.asarray(gp.L_, float))
                out.length_scale[j] = torch.as_tensor(ell)
                out.signal_var[j] = s
                out.noise_var[j] = noise
                out.y_mean[j] = float(np.ravel(gp._y_train_mean)[0])
                out.y_std[j] = float(np.ravel(gp._y_train_std)[0])
            out.pca_mean.copy_(torch.as_tensor(b.pca.mean_))
            out.components.copy_(torch.as_tensor(b.pca.components_))
        return out

    def _cross(self, u: torch.Tensor) -> torch.Tensor:
        """Kernel matrices ``k_j(u, X) / s_j``: ``(k, b, n_rows)``."""
        a = u[None, :, :] / self.length_scale[:, None, :]  # (k, b, d)
        x = self.x_train[None, :, :] / self.length_scale[:, None, :]  # (k, n, d)
        r2 = (a * a).sum(-1)[:, :, None] + (x * x).sum(-1)[:, None, :] \
            - 2.0 * a @ x.transpose(1, 2)
        r = torch.sqrt(r2.clamp_min(0.0) + 1e-30)  # smooth at r = 0 for autograd
        return (1.0 + SQRT5 * r + (5.0 / 3.0) * r * r) * torch.exp(-SQRT5 * r)

    def forward(self, u: torch.Tensor, variance: bool = True
                ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Unit parameters ``(b, d)`` -> (mean ``(b, m)``, latent variance ``(b, m)`` or
        None when ``variance`` is False) in normalised cube-root units, in ``u``'s dtype;
        differentiable in ``u``."""
        ud = u.to(torch.float64)
        kx = self._cross(ud) * self.signal_var[:, None, None]  # (k, b, n)
        mean_s = (kx @ self.alpha[:, :, None])[..., 0]  # (k, b)
        mean_s = self.y_mean[:, None] + self.y_std[:, None] * mean_s
        mean = (self.pca_mean + mean_s.T @ self.components).to(u.dtype)  # (b, m)
        if not variance:
            return mean, None
        v = torch.linalg.solve_triangular(self.chol, kx.transpose(1, 2), upper=False)
        reduce = (v * v).sum(1)  # k K^-1 k^T = |L^-1 k^T|^2, (k, b)
        var_s = (self.signal_var[:, None] - reduce).clamp_min(0.0) * self.y_std[:, None] ** 2
        return mean, (var_s.T @ (self.components ** 2)).to(u.dtype)


def fit_pressure_gp(u: np.ndarray, y: np.ndarray, n_components: int = 8, seed: int = 0
                    ) -> tuple[GPPressure, dict]:
    """Fit :class:`PCAGPBaseline` on unit parameters ``u (n, d)`` and normalised curves
    ``y (n, m)``; returns it as a :class:`GPPressure` and a JSON description (rows,
    components and their explained variance, fitted kernel per component, seconds)."""
    t0 = time.perf_counter()
    b = PCAGPBaseline(n_components, seed).fit(u, y)
    gp = GPPressure.from_baseline(b)
    kernels = []
    for g in b.gps:
        s, ell, noise = _kernel_parts(g)
        kernels.append({"signal_var": s, "length_scale": ell.tolist(), "noise_var": noise,
                        "log_marginal_likelihood": float(g.log_marginal_likelihood_value_)})
    return gp, {"n_rows": len(u), "n_components": len(b.gps),
                "explained_variance_ratio": [float(v) for v in
                                             b.pca.explained_variance_ratio_],
                "kernel": "ConstantKernel * Matern(nu=2.5) + WhiteKernel, per component "
                          "(scores normalised; unit parameters)",
                "components": kernels, "fit_seconds": time.perf_counter() - t0}


__all__ = ["GPPressure", "fit_pressure_gp"]

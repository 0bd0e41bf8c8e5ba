"""Analytic stand-ins for a trained surrogate (same interface as ``surrogate.load``).

:class:`LinearSurrogate` predicts normalised pressure that is linear in the unit parameters
(orthogonal Legendre shapes along the depth), so the least-squares minimiser and the
linear-Gaussian posterior are known in closed form; its distribution is a Gaussian blob whose
centre moves with three parameters. It records the extreme inputs it was called with.
"""

from __future__ import annotations

import numpy as np
import torch

from calendaring.data.params import PAPER_SPACE

STROKE = 19.5e-6  # m
N_POINTS = 196
CBRT_MAX = 3e8 ** (1.0 / 3.0)  # Pa^(1/3): normalised 1 = 300 MPa


class Prediction:
    def __init__(self, pressure, pressure_normalised, distribution, std):
        self.pressure = pressure
        self.pressure_normalised = pressure_normalised
        self.distribution = distribution
        self.pressure_std = std
        self.distribution_std = None


class LinearSurrogate:
    """p_norm(u) = b(z) + A(z) u  (A: 8 Legendre shapes x ``amplitude``)."""

    def __init__(self, amplitude: float = 0.08, var: float | None = None, blob: bool = True):
        self.space = PAPER_SPACE
        edges = np.linspace(0.0, STROKE, N_POINTS + 1)
        self.depth = 0.5 * (edges[1:] + edges[:-1])
        self.load_edges = np.geomspace(1e-3, 1.0, 31)
        self.diameter_edges = np.linspace(4e-6, 16e-6, 31)
        self.is_ensemble = var is not None
        x = 2 * self.depth / STROKE - 1  # [-1, 1]
        shapes = np.stack([np.polynomial.legendre.Legendre.basis(k + 1)(x) for k in range(8)],
                          axis=1)  # (196, 8)
        self.A = amplitude * shapes
        self.b = 0.5 * (self.depth / STROKE) ** 0.7 + 0.1
        self.var = var
        self.blob = blob
        self.calls = 0
        self.distribution_calls = 0  # calls that asked for the distribution
        self.u_min, self.u_max = np.inf, -np.inf
        lc = np.sqrt(self.load_edges[:-1] * self.load_edges[1:])
        self._ll = torch.as_tensor((np.log(lc) - np.log(1e-3)) / np.log(1e3), dtype=torch.float32)
        dc = 0.5 * (self.diameter_edges[1:] + self.diameter_edges[:-1])
        self._dd = torch.as_tensor((dc - 4e-6) / 12e-6, dtype=torch.float32)

    # ---------------------------------------------------------------- normalisation
    def normalise_pressure(self, p):
        if isinstance(p, torch.Tensor):
            return torch.sign(p) * torch.abs(p) ** (1 / 3) / CBRT_MAX
        return np.cbrt(np.asarray(p, float)) / CBRT_MAX

    def pressure_from_normalised(self, x):
        return (x * CBRT_MAX) ** 3

    # ---------------------------------------------------------------- forward
    def p_norm_numpy(self, u) -> np.ndarray:
        return self.b[None, :] + np.atleast_2d(u) @ self.A.T

    def torch_forward(self, u: torch.Tensor, distribution: bool = True):
        self.calls += 1
        self.distribution_calls += int(distribution)
        un = u.detach().numpy()
        self.u_min = min(self.u_min, float(un.min()))
        self.u_max = max(self.u_max, float(un.max()))
        A = torch.as_tensor(self.A, dtype=u.dtype)
        b = torch.as_tensor(self.b, dtype=u.dtype)
        p = b + u @ A.T  # (n, 196)
        var = None if self.var is None else torch.full_like(p, self.var)
        if not distribution:
            return p, None, var
        if not self.blob:  # a fixed uniform distribution (cheaper; no centroid information)
            return p, torch.full((len(u), 30, 30), 1.0 / 900, dtype=u.dtype), var
        # blob: load centre from u[2] (d0), diameter centre from u[3] (phi)
        cl = 0.2 + 0.6 * u[:, 2:3]
        cd = 0.2 + 0.6 * u[:, 3:4]
        logits = (-0.5 * ((self._ll[None, :, None] - cl[:, :, None]) / 0.15) ** 2
                  - 0.5 * ((self._dd[None, None, :] - cd[:, :, None]) / 0.15) ** 2)
        d = torch.softmax(logits.reshape(len(u), -1), dim=1).reshape(len(u), 30, 30)
        return p, d, var

    def predict_unit(self, u):
        with torch.no_grad():
            p, d, var = self.torch_forward(torch.as_tensor(np.atleast_2d(u), dtype=torch.float32))
        p = p.double().numpy()
        std = None
        if var is not None:
            c = p * CBRT_MAX
            std = np.sqrt(var.double().numpy()) * 3 * c ** 2 * CBRT_MAX
        return Prediction(self.pressure_from_normalised(p), p, d.double().numpy(), std)

    def predict(self, params):
        return self.predict_unit(self.space.to_unit(np.atleast_2d(params)))

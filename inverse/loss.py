"""The composite calibration loss of paper section 2.4, evaluated on the surrogate.

For unit parameters ``u`` (rows in ``[0, 1]^8``) the loss is

    L(u) = w_p L_p(u) + w_c L_c(u) + w_b L_b(u),      w_p + w_c + w_b = 1,

* ``L_p``: weighted Huber loss between predicted and target pressure in the surrogate's
  normalised cube-root units, on the valid (covered) target points only, with weights
  ``exp(k y_i / max y)`` (``y`` the normalised target, ``k`` = ``load_emphasis``) normalised
  to sum to 1, so that points at higher load count more; the Huber loss is divided by its
  ``delta`` so that large residuals count as ``|r|`` and small ones as ``r^2 / (2 delta)``;
* ``L_c``: squared distance between the predicted distribution's centroid (load, diameter) and
  the target centroid, both axes scaled to ``[0, 1]`` by the model's bin edges (the load axis
  logarithmically when the edges are geometric), with the centroid of
  :func:`calendaring.data.dataset.centroids`, here differentiable in torch;
* ``L_b``: the boundary penalty ``mean_j [exp(-u_j / s) + exp(-(1 - u_j) / s)]`` over the free
  parameters, which grows exponentially as any parameter approaches 0 or 1 (``s`` =
  ``boundary_scale``).

The weights are normalised over the active terms (the centroid term is inactive without a
target centroid). All functions take a batch ``u`` of shape (n, 8) and return (n,) losses, so
restarts can be evaluated together.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import asdict, dataclass

import numpy as np
import torch

from calendaring import ConfigError
from inverse.targets import Target, bin_centres


@dataclass(frozen=True)
class LossConfig:
    """Term weights (normalised to sum 1 over the active terms) and shape constants."""

    pressure_weight: float = 1.0
    centroid_weight: float = 0.25
    boundary_weight: float = 0.05
    huber_delta: float = 0.02  # normalised pressure units: quadratic below, linear above
    load_emphasis: float = 2.0  # k in exp(k y / max y)
    boundary_scale: float = 0.02  # e-folding distance from a bound, unit-parameter space

    def __post_init__(self) -> None:
        for key in ("pressure_weight", "centroid_weight", "boundary_weight", "load_emphasis"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"loss.{key}", v, ">= 0")
        for key in ("huber_delta", "boundary_scale"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"loss.{key}", v, "> 0")
        if self.pressure_weight <= 0:
            raise ConfigError("loss.pressure_weight", self.pressure_weight, "> 0")

    def to_json(self) -> dict:
        return asdict(self)


@contextmanager
def weights_frozen(model):
    """Turn off gradients of the surrogate's weights for the duration (restored after).

    Calibration needs gradients with respect to the inputs only; not tracking the weights
    also avoids the weight-gradient reductions of the backward pass (on CPU, the LayerNorm
    weight gradients alone made an input gradient ~20x slower than the forward pass).
    """
    mods = [model] if isinstance(model, torch.nn.Module) else []
    mods += [m for m in (getattr(model, "members", None) or []) if isinstance(m, torch.nn.Module)]
    params = [p for mod in mods for p in mod.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield model
    finally:
        for p in params:
            p.requires_grad_(True)


def boundary_penalty(u: torch.Tensor, scale: float, free: torch.Tensor | None = None
                     ) -> torch.Tensor:
    """Exponential barrier ``mean_j [exp(-u_j/s) + exp(-(1-u_j)/s)]`` over the free columns.

    Args:
        u: (n, d) unit parameters.
        scale: ``s``, the e-folding distance from a bound.
        free: (d,) bool mask of the columns that count (all if None).
    Returns:
        (n,) penalty, 2 exp(-1/(2s)) at the centre of the cube and ~1 at a bound.
    """
    b = torch.exp(-u / scale) + torch.exp(-(1.0 - u) / scale)  # (n, d)
    if free is not None:
        b = b[:, free]
    return b.mean(dim=1)


def torch_centroids(dist: torch.Tensor, load_axis: torch.Tensor, diameter_centres: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Probability-weighted centroid of histograms (n, L, D), differentiable.

    ``load_axis`` is log(load centres) for a log axis (geometric centroid) or the centres
    themselves; returns (load-axis coordinate, diameter [m]), each (n,).
    """
    w = dist.sum(dim=(-1, -2))  # (n,)
    cl = dist.sum(dim=-1) @ load_axis / w  # (n,)
    cd = dist.sum(dim=-2) @ diameter_centres / w  # (n,)
    return cl, cd


class CompositeLoss:
    """The paper's inverse loss for one target and one surrogate (see the module docstring).

    Args:
        model: an object with the surrogate API (``torch_forward``, ``normalise_pressure``,
            ``depth``, ``load_edges``, ``diameter_edges``).
        target: a :class:`~inverse.targets.Target` on ``model.depth``.
        config: weights and shape constants.
        free: (8,) bool mask of free parameters (boundary penalty only on these).
    """

    def __init__(self, model, target: Target, config: LossConfig | None = None,
                 free: np.ndarray | None = None) -> None:
        self.model = model
        self.target = target
        self.config = config or LossConfig()
        n = len(model.space) if hasattr(model, "space") else 8
        self.free = torch.as_tensor(np.ones(n, bool) if free is None else np.asarray(free, bool))
        if len(target.depth) != len(model.depth) or not np.allclose(
                target.depth, model.depth, rtol=1e-6, atol=1e-12):
            raise ConfigError("target.depth", f"{len(target.depth)} points",
                              f"the model's {len(model.depth)} depths (resample the target "
                              "with inverse.targets)")
        valid = np.asarray(target.valid, bool) & np.isfinite(target.pressure)
        self.valid = torch.as_tensor(valid)
        y = np.asarray(model.normalise_pressure(np.where(valid, target.pressure, 0.0)), float)
        self.y = torch.as_tensor(np.where(valid, y, 0.0), dtype=torch.float32)  # (m,)
        yv = y[valid]
        ref = max(float(np.max(np.abs(yv))), 1e-12)
        w = np.where(valid, np.exp(self.config.load_emphasis * np.clip(y, 0, None) / ref), 0.0)
        self.point_weight = torch.as_tensor(w / w.sum(), dtype=torch.float32)  # (m,), sums 1
        # centroid axes scaled to [0, 1] by the model's edges
        lc, dc, log = bin_centres(model.load_edges, model.diameter_edges)
        le, de = np.asarray(model.load_edges, float), np.asarray(model.diameter_edges, float)
        if log:
            self._l_axis, l0, l1 = np.log(lc), np.log(le[0]), np.log(le[-1])
        else:
            self._l_axis, l0, l1 = lc, le[0], le[-1]
        self._l_range = (l0, l1)
        self._d_range = (de[0], de[-1])
        self.l_axis_t = torch.as_tensor((self._l_axis - l0) / (l1 - l0), dtype=torch.float32)
        self.d_axis_t = torch.as_tensor((dc - de[0]) / (de[-1] - de[0]), dtype=torch.float32)
        self.has_centroid = target.centroids is not None and np.all(
            np.isfinite(target.centroids))
        if self.has_centroid:
            self.c_target = torch.as_tensor(self.scale_centroid(target.centroids),
                                            dtype=torch.float32)
        raw = {"pressure": self.config.pressure_weight,
               "centroid": self.config.centroid_weight if self.has_centroid else 0.0,
               "boundary": self.config.boundary_weight}
        total = sum(raw.values())
        self.weights = {k: v / total for k, v in raw.items()}

    # ------------------------------------------------------------------ helpers
    def scale_centroid(self, c) -> np.ndarray:
        """(load [N], diameter [m]) -> the two centroid coordinates scaled to [0, 1]."""
        c = np.asarray(c, float)
        lc = np.log(c[..., 0]) if is_log(self) else c[..., 0]
        l0, l1 = self._l_range
        d0, d1 = self._d_range
        return np.stack([(lc - l0) / (l1 - l0), (c[..., 1] - d0) / (d1 - d0)], axis=-1)

    def unscale_centroid(self, s) -> np.ndarray:
        """Inverse of :meth:`scale_centroid`."""
        s = np.asarray(s, float)
        l0, l1 = self._l_range
        d0, d1 = self._d_range
        lc = l0 + s[..., 0] * (l1 - l0)
        return np.stack([np.exp(lc) if is_log(self) else lc, d0 + s[..., 1] * (d1 - d0)],
                        axis=-1)

    def predicted_centroid(self, dist: torch.Tensor) -> torch.Tensor:
        """(n, L, D) distributions -> (n, 2) scaled centroids."""
        cl, cd = torch_centroids(dist, self.l_axis_t, self.d_axis_t)
        return torch.stack([cl, cd], dim=-1)

    # ------------------------------------------------------------------ evaluation
    def terms(self, u: torch.Tensor) -> dict[str, torch.Tensor]:
        """Each term (unweighted), (n,) tensors, plus the weighted ``total``."""
        p_norm, dist, _ = self.model.torch_forward(  # (n, m), (n, L, D) or None
            u, distribution=self.has_centroid)
        h = torch.nn.functional.huber_loss(p_norm, self.y.expand_as(p_norm), reduction="none",
                                           delta=self.config.huber_delta)
        h = torch.where(self.valid, h, torch.zeros_like(h))
        lp = (h * self.point_weight).sum(dim=1) / self.config.huber_delta  # ~ |r| for |r| > delta
        lb = boundary_penalty(u, self.config.boundary_scale, self.free)
        out = {"pressure": lp, "boundary": lb}
        total = self.weights["pressure"] * lp + self.weights["boundary"] * lb
        if self.has_centroid:
            lc = ((self.predicted_centroid(dist) - self.c_target) ** 2).sum(dim=1)
            out["centroid"] = lc
            total = total + self.weights["centroid"] * lc
        out["total"] = total
        return out

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """(n, 8) unit parameters -> (n,) total loss."""
        return self.terms(u)["total"]

    def evaluate(self, u) -> dict[str, np.ndarray]:
        """NumPy in, NumPy out, no gradient: every term at rows ``u`` (n, 8)."""
        with torch.no_grad():
            t = self.terms(torch.as_tensor(np.atleast_2d(u), dtype=torch.float32))
        return {k: v.detach().double().numpy() for k, v in t.items()}


def is_log(loss: CompositeLoss) -> bool:
    """Whether the loss's load axis is logarithmic."""
    from inverse.targets import is_log_axis

    return is_log_axis(loss.model.load_edges)


__all__ = ["CompositeLoss", "LossConfig", "boundary_penalty", "torch_centroids",
           "weights_frozen"]

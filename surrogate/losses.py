"""The paper's training loss: weighted pressure MSE plus distribution KL divergence.

``total = w_p * MSE(p_pred, p_true) + w_d * KL(d_true || d_pred)`` with ``w_p = 0.7`` and
``w_d = 0.3`` (Table 3's totals equal 0.7 MSE + 0.3 KL exactly). The MSE is the mean over
all rows and depths in normalised cube-root units. The KL is summed over the 900 bins and
averaged over rows, both histograms floored at 1e-8 and renormalised first, the same
quantity as :func:`calendaring.data.dataset.kl_divergence`. Rows without breakage events
(``kl_weight = 0``) are left out of the KL mean.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from calendaring import KL_FLOOR, ConfigError

MSE_WEIGHT = 0.7  # paper, Table 3
KL_WEIGHT = 0.3


@dataclass(frozen=True)
class LossTerms:
    """One evaluation of :class:`SurrogateLoss`: the total and both components (tensors)."""

    total: torch.Tensor
    mse: torch.Tensor
    kl: torch.Tensor

    def item(self) -> dict[str, float]:
        return {"total": float(self.total.detach()), "mse": float(self.mse.detach()),
                "kl": float(self.kl.detach())}


def kl_per_row(d_true: torch.Tensor, d_pred: torch.Tensor, floor: float = KL_FLOOR
               ) -> torch.Tensor:
    """KL(d_true || d_pred) of ``(n, L, D)`` histograms -> ``(n,)`` with the 1e-8 floor."""
    p = (d_true + floor).flatten(1)  # (n, 900)
    q = (d_pred + floor).flatten(1)
    p = p / p.sum(dim=1, keepdim=True)
    q = q / q.sum(dim=1, keepdim=True)
    return torch.sum(p * (torch.log(p) - torch.log(q)), dim=1)


class SurrogateLoss(nn.Module):
    """``mse_weight * MSE + kl_weight * KL``; returns :class:`LossTerms`."""

    def __init__(self, mse_weight: float = MSE_WEIGHT, kl_weight: float = KL_WEIGHT,
                 floor: float = KL_FLOOR):
        super().__init__()
        if mse_weight < 0 or kl_weight < 0 or mse_weight + kl_weight <= 0:
            raise ConfigError("loss weights", (mse_weight, kl_weight),
                              "non-negative, not both zero")
        self.mse_weight = float(mse_weight)
        self.kl_weight = float(kl_weight)
        self.floor = float(floor)

    def forward(self, p_pred: torch.Tensor, p_true: torch.Tensor, d_pred: torch.Tensor,
                d_true: torch.Tensor, kl_weight: torch.Tensor | None = None) -> LossTerms:
        mse = torch.mean((p_pred - p_true) ** 2)
        kl_rows = kl_per_row(d_true, d_pred, self.floor)  # (n,)
        if kl_weight is None:
            kl = kl_rows.mean()
        else:
            kl = torch.sum(kl_rows * kl_weight) / torch.clamp(kl_weight.sum(), min=1.0)
        return LossTerms(self.mse_weight * mse + self.kl_weight * kl, mse, kl)


__all__ = ["KL_WEIGHT", "MSE_WEIGHT", "LossTerms", "SurrogateLoss", "kl_per_row"]

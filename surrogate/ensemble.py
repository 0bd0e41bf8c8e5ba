"""Deep ensembles of the dual-branch MLP (Lakshminarayanan et al. 2017, NeurIPS 30).

Members share the training split and the normalisation and differ in their initial weights,
batch order and dropout masks (:attr:`TrainConfig.member`). The predictive mean is the
member mean; the variance is the spread between members (population variance, ``ddof = 0``,
so it is non-negative and exactly zero when all members agree). It measures epistemic
uncertainty only, not the run-to-run noise of the simulations (see the replicate noise floor
in :mod:`surrogate.evaluate`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import torch

from calendaring import ConfigError, Dataset
from surrogate.model import DualBranchMLP, ModelConfig
from surrogate.train import TrainConfig, TrainResult, make_split, train

DEFAULT_MEMBERS = 5


def ensemble_forward(members: Sequence[DualBranchMLP], u: torch.Tensor,
                     distribution: bool = True
                     ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None,
                                torch.Tensor | None]:
    """Mean and variance over members (differentiable in ``u``; members as they are set).

    Returns ``(p_mean (n, 196), d_mean (n, 30, 30), p_var (n, 196), d_var (n, 30, 30))``;
    the variances are None for a single member. The mean distribution still sums to 1.
    With ``distribution=False`` only the pressure branch runs and both distribution
    outputs are None (about 5x fewer multiply-adds: what a pressure-only likelihood needs).
    """
    if not distribution:
        p = torch.stack([m.forward_pressure(u) for m in members])  # (m, n, 196)
        if len(members) == 1:
            return p[0], None, None, None
        return p.mean(0), None, p.var(0, unbiased=False), None
    outs = [m(u) for m in members]
    if len(outs) == 1:
        return outs[0][0], outs[0][1], None, None
    p = torch.stack([o[0] for o in outs])  # (m, n, 196)
    d = torch.stack([o[1] for o in outs])  # (m, n, 30, 30)
    return p.mean(0), d.mean(0), p.var(0, unbiased=False), d.var(0, unbiased=False)


def train_ensemble(ds: Dataset, n_members: int = DEFAULT_MEMBERS, cfg: TrainConfig | None = None,
                   model_config: ModelConfig | None = None, progress: bool = True
                   ) -> list[TrainResult]:
    """Train ``n_members`` models on the same split and normalisation (member seeds differ)."""
    if int(n_members) < 1:
        raise ConfigError("--ensemble", n_members, "an integer >= 1")
    cfg = cfg or TrainConfig()
    split = make_split(ds, cfg)
    results: list[TrainResult] = []
    for k in range(int(n_members)):
        res = train(ds, replace(cfg, member=k), model_config, progress=progress, split=split,
                    norm=results[0].normalisation if results else None)
        results.append(res)
    return results


__all__ = ["DEFAULT_MEMBERS", "ensemble_forward", "train_ensemble"]

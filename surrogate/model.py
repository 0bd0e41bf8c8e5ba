"""The paper's dual-branch multilayer perceptron (section 2.3, Fig. 4).

Eight unit parameters in ``[0, 1]`` go through a shared feature extractor::

    Linear(8, 256) -> LeakyReLU(0.1) -> Dropout(0.3)
    ResidualBlock(256, 128) -> ResidualBlock(128, 64)

where each residual block is ``LayerNorm(Dropout(LeakyReLU(Linear(x))) + Linear_skip(x))``
(the skip is the identity when the widths match). The 64-wide embedding feeds two heads:

- pressure: ``Linear(64, 128) -> ReLU -> Dropout -> Linear(128, 196) -> Softplus``, the
  normalised cube-root pressure at the 196 depths (strictly positive);
- distribution: ``Linear(64, 256) -> ReLU -> Dropout -> Linear(256, 512) -> ReLU -> Dropout
  -> Linear(512, 900)``, a softmax over all 900 bins, reshaped to ``(30, 30)``
  [peak-load bin, parent-diameter bin].

All widths and the dropout rate live in the frozen :class:`ModelConfig`, which checkpoints
store so that a model can be rebuilt from its file alone.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from calendaring import ConfigError


@dataclass(frozen=True, slots=True, kw_only=True)
class ModelConfig:
    """Architecture of :class:`DualBranchMLP`; the defaults are the paper's (Fig. 4)."""

    n_inputs: int = 8  # breakage parameters, unit-scaled
    embed_width: int = 256  # first linear layer
    block_widths: tuple[int, ...] = (128, 64)  # residual blocks 256 -> 128 -> 64
    pressure_hidden: int = 128  # pressure head hidden width
    n_pressure: int = 196  # depths of the pressure curve
    dist_hidden: tuple[int, ...] = (256, 512)  # distribution head hidden widths
    dist_shape: tuple[int, int] = (30, 30)  # [load bins, diameter bins]
    dropout: float = 0.3  # uniform across the network
    negative_slope: float = 0.1  # LeakyReLU of the shared extractor

    def __post_init__(self) -> None:
        for key in ("n_inputs", "embed_width", "pressure_hidden", "n_pressure"):
            if int(getattr(self, key)) < 1:
                raise ConfigError(f"model.{key}", getattr(self, key), "an integer >= 1")
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError("model.dropout", self.dropout, "0 <= dropout < 1")
        if len(self.dist_shape) != 2 or min(self.dist_shape) < 1:
            raise ConfigError("model.dist_shape", self.dist_shape, "two positive integers")

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError("model", unknown, f"keys among {sorted(known)}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


class ResidualBlock(nn.Module):
    """``LayerNorm(Dropout(LeakyReLU(W x + b)) + P x)``; ``P`` is a linear projection when
    ``in_dim != out_dim`` and the identity otherwise (paper section 2.3)."""

    def __init__(self, in_dim: int, out_dim: int, dropout: float, negative_slope: float):
        super().__init__()
        self.fc = nn.Linear(in_dim, out_dim)
        self.act = nn.LeakyReLU(negative_slope)
        self.drop = nn.Dropout(dropout)
        self.skip = nn.Linear(in_dim, out_dim) if in_dim != out_dim else nn.Identity()
        self.norm = nn.LayerNorm(out_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(self.drop(self.act(self.fc(x))) + self.skip(x))  # (n, out_dim)


class DualBranchMLP(nn.Module):
    """Unit parameters ``(n, 8)`` -> (normalised pressure ``(n, 196)``, distribution
    ``(n, 30, 30)``); see the module docstring for the layers."""

    def __init__(self, config: ModelConfig | None = None):
        super().__init__()
        self.config = cfg = config or ModelConfig()
        layers: list[nn.Module] = [nn.Linear(cfg.n_inputs, cfg.embed_width),
                                   nn.LeakyReLU(cfg.negative_slope), nn.Dropout(cfg.dropout)]
        width = cfg.embed_width
        for w in cfg.block_widths:
            layers.append(ResidualBlock(width, w, cfg.dropout, cfg.negative_slope))
            width = w
        self.features = nn.Sequential(*layers)
        self.pressure_head = nn.Sequential(
            nn.Linear(width, cfg.pressure_hidden), nn.ReLU(), nn.Dropout(cfg.dropout),
            nn.Linear(cfg.pressure_hidden, cfg.n_pressure), nn.Softplus())
        dist: list[nn.Module] = []
        w_in = width
        for w in cfg.dist_hidden:
            dist += [nn.Linear(w_in, w), nn.ReLU(), nn.Dropout(cfg.dropout)]
            w_in = w
        dist.append(nn.Linear(w_in, cfg.dist_shape[0] * cfg.dist_shape[1]))
        self.dist_head = nn.Sequential(*dist)

    def forward_logits(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(normalised pressure ``(n, 196)``, distribution logits ``(n, 900)``)."""
        h = self.features(u)  # (n, 64)
        return self.pressure_head(h), self.dist_head(h)

    def forward_pressure(self, u: torch.Tensor) -> torch.Tensor:
        """Normalised pressure ``(n, 196)`` alone: the distribution head (most of the
        multiply-adds) is skipped, for callers that never read the distribution."""
        return self.pressure_head(self.features(u))

    def forward(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        p, logits = self.forward_logits(u)  # (n, 196), (n, 900)
        dist = torch.softmax(logits, dim=-1)  # over all 900 bins
        return p, dist.reshape(-1, *self.config.dist_shape)  # (n, 196), (n, 30, 30)

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


__all__ = ["DualBranchMLP", "ModelConfig", "ResidualBlock"]

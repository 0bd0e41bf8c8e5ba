"""Training of the dual-branch MLP (paper section 2.3): split, trainer, histories, collector.

:func:`train` is the paper's encapsulation function: it selects the trainable rows, splits
them 8:1:1 with a seed, fits the normalisation on the training split only, builds the model,
:class:`~surrogate.losses.SurrogateLoss` and Adam with weight decay, runs a
:class:`Trainer` for ``epochs`` epochs with early stopping on the validation loss (the best
weights are restored), and evaluates the loss table (Table 3) on the three splits. A
:class:`Collector` keeps true and predicted samples at chosen epochs for the PCA
convergence figure (Fig. 5).

Everything is seeded from :attr:`TrainConfig.seed` (split, initial weights, batch order,
dropout): two calls with the same data and configuration give identical weights on the same
machine and thread count.
"""

from __future__ import annotations

import copy
import sys
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from tqdm.auto import tqdm

from calendaring import ConfigError, Dataset
from surrogate.data import (
    TRAIN_ROLES_DEFAULT,
    Normalisation,
    SurrogateDataset,
    split_indices,
    trainable_rows,
)
from surrogate.losses import KL_WEIGHT, MSE_WEIGHT, SurrogateLoss
from surrogate.model import DualBranchMLP, ModelConfig

PRESSURE_HEADS = ("mlp", "gp")


@dataclass(frozen=True, slots=True, kw_only=True)
class TrainConfig:
    """Training settings. ``patience = 0`` turns early stopping off (best weights are still
    restored); ``member`` offsets the seed of the weights and batch order (deep ensembles)
    while the split stays that of ``seed``."""

    epochs: int = 80  # paper: 80
    batch_size: int = 16
    lr: float = 1e-3  # Adam learning rate
    weight_decay: float = 1e-5  # Adam weight decay (L2)
    patience: int = 20  # epochs without validation improvement before stopping
    seed: int = 0
    member: int = 0
    mse_weight: float = MSE_WEIGHT
    kl_weight: float = KL_WEIGHT
    train_roles: tuple[str, ...] = TRAIN_ROLES_DEFAULT
    split: tuple[float, float, float] = (0.8, 0.1, 0.1)
    snapshot_epochs: tuple[int, ...] = (10, 40, 80)  # Fig. 5 panels
    collector_max: int = 512  # samples kept per snapshot
    # "gp": predictions take the pressure from a PCA + GP branch fitted on the training and
    # validation rows (surrogate.gp); the network is trained as usual and gives the
    # distribution
    pressure_head: str = "mlp"
    gp_components: int = 8  # principal components of the GP branch

    def __post_init__(self) -> None:
        for key, lo in (("epochs", 1), ("batch_size", 1), ("patience", 0), ("collector_max", 1),
                        ("gp_components", 1)):
            v = getattr(self, key)
            if not isinstance(v, int | np.integer) or v < lo:
                raise ConfigError(f"--{key.replace('_', '-')}", v, f"an integer >= {lo}")
        if not (self.lr > 0 and np.isfinite(self.lr)):
            raise ConfigError("--lr", self.lr, "a positive number")
        if not (self.weight_decay >= 0 and np.isfinite(self.weight_decay)):
            raise ConfigError("--weight-decay", self.weight_decay, "a number >= 0")
        for key in ("mse_weight", "kl_weight"):
            v = getattr(self, key)
            if not (v >= 0 and np.isfinite(v)):
                raise ConfigError(f"--{key.replace('_', '-')}", v, "a finite number >= 0")
        if self.pressure_head not in PRESSURE_HEADS:
            raise ConfigError("--pressure-head", self.pressure_head, f"one of {PRESSURE_HEADS}")
        if self.mse_weight + self.kl_weight <= 0:
            raise ConfigError("--mse-weight + --kl-weight", self.mse_weight + self.kl_weight,
                              "> 0 (not both weights zero)")

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        known = set(cls.__dataclass_fields__)
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()
                      if k in known})


class Collector:
    """Keeps true and predicted samples for visualisation (paper section 2.3).

    Pressure curves: every batch until ``max_samples`` rows. Distributions: a random subset
    of at most ``dist_per_batch`` rows of each batch (seeded), up to ``max_samples``.
    """

    def __init__(self, max_samples: int = 512, dist_per_batch: int = 64, seed: int = 0):
        self.max_samples = int(max_samples)
        self.dist_per_batch = int(dist_per_batch)
        self._rng = np.random.default_rng(seed)
        self._p_true: list[np.ndarray] = []
        self._p_pred: list[np.ndarray] = []
        self._d_true: list[np.ndarray] = []
        self._d_pred: list[np.ndarray] = []

    def _count(self, parts) -> int:
        return sum(len(a) for a in parts)

    def add(self, p_true, p_pred, d_true, d_pred) -> None:
        """Add one batch (tensors or arrays): ``(n, 196)`` pressures, ``(n, 30, 30)`` maps."""
        p_true, p_pred, d_true, d_pred = (
            np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float32)
            for x in (p_true, p_pred, d_true, d_pred))
        room = self.max_samples - self._count(self._p_true)
        if room > 0:
            self._p_true.append(p_true[:room])
            self._p_pred.append(p_pred[:room])
        room = self.max_samples - self._count(self._d_true)
        if room > 0:
            k = min(len(d_true), self.dist_per_batch, room)
            pick = np.sort(self._rng.choice(len(d_true), size=k, replace=False))
            self._d_true.append(d_true[pick])
            self._d_pred.append(d_pred[pick])

    def arrays(self) -> dict[str, np.ndarray]:
        """``pressure_true``, ``pressure_pred`` ``(m, 196)``; ``dist_true``, ``dist_pred``
        ``(k, 30, 30)`` (empty arrays before any batch)."""
        def cat(parts, shape):
            return np.concatenate(parts) if parts else np.zeros((0, *shape), np.float32)
        return {"pressure_true": cat(self._p_true, (0,)), "pressure_pred": cat(self._p_pred, (0,)),
                "dist_true": cat(self._d_true, (0, 0)), "dist_pred": cat(self._d_pred, (0, 0))}


@dataclass
class History:
    """Per-epoch losses (training: running mean with dropout; validation: eval mode)."""

    train_total: list[float] = field(default_factory=list)
    train_mse: list[float] = field(default_factory=list)
    train_kl: list[float] = field(default_factory=list)
    val_total: list[float] = field(default_factory=list)
    val_mse: list[float] = field(default_factory=list)
    val_kl: list[float] = field(default_factory=list)
    best_epoch: int = 0  # 1-based epoch whose weights were kept
    stopped_early: bool = False

    def append(self, prefix: str, terms: dict[str, float]) -> None:
        for k in ("total", "mse", "kl"):
            getattr(self, f"{prefix}_{k}").append(float(terms[k]))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> History:
        return cls(**d)


class Trainer:
    """Runs epochs of Adam on a model with :class:`SurrogateLoss`; records a :class:`History`."""

    def __init__(self, model: DualBranchMLP, loss: SurrogateLoss,
                 optimizer: torch.optim.Optimizer, progress: bool = True, desc: str = "train"):
        self.model = model
        self.loss = loss
        self.optimizer = optimizer
        self.progress = progress
        self.desc = desc
        self.history = History()

    def train_epoch(self, loader: torch.utils.data.DataLoader) -> dict[str, float]:
        """One pass over ``loader`` with gradient steps; row-weighted mean losses."""
        self.model.train()
        sums, n = {"total": 0.0, "mse": 0.0, "kl": 0.0}, 0
        for u, p, d, w in loader:
            self.optimizer.zero_grad(set_to_none=True)
            p_hat, d_hat = self.model(u)  # (b, 196), (b, 30, 30)
            terms = self.loss(p_hat, p, d_hat, d, w)
            terms.total.backward()
            self.optimizer.step()
            for k, v in terms.item().items():
                sums[k] += v * len(u)
            n += len(u)
        return {k: v / max(n, 1) for k, v in sums.items()}

    @torch.no_grad()
    def evaluate(self, data: SurrogateDataset, collector: Collector | None = None
                 ) -> dict[str, float]:
        """Losses of the whole split in eval mode (no dropout); optionally collects samples."""
        self.model.eval()
        if len(data) == 0:
            return {"total": float("nan"), "mse": float("nan"), "kl": float("nan")}
        u, p, d, w = data.tensors()
        p_hat, d_hat = self.model(u)
        if collector is not None:
            collector.add(p, p_hat, d, d_hat)
        return self.loss(p_hat, p, d_hat, d, w).item()

    def fit(self, train_loader, val_data: SurrogateDataset, epochs: int, patience: int = 0,
            snapshot_epochs: tuple[int, ...] = (), snapshot_data: SurrogateDataset | None = None,
            collector_max: int = 512, seed: int = 0) -> dict[int, dict[str, np.ndarray]]:
        """Train for ``epochs`` epochs; early stop after ``patience`` epochs without a lower
        validation total (0: never); restore the best weights. Returns the collected
        samples ``{epoch: Collector.arrays()}`` of ``snapshot_data`` at ``snapshot_epochs``
        (and at the last epoch run)."""
        best, best_state, since = float("inf"), None, 0
        snapshots: dict[int, dict[str, np.ndarray]] = {}
        snap_data = snapshot_data if snapshot_data is not None else val_data
        bar = tqdm(range(1, epochs + 1), desc=self.desc, file=sys.stderr, leave=False,
                   disable=not self.progress, unit="epoch")
        epoch = 0
        for epoch in bar:
            self.history.append("train", self.train_epoch(train_loader))
            val = self.evaluate(val_data)
            self.history.append("val", val)
            if epoch in snapshot_epochs:
                c = Collector(collector_max, seed=seed + epoch)
                self.evaluate(snap_data, c)
                snapshots[epoch] = c.arrays()
            bar.set_postfix(train=f"{self.history.train_total[-1]:.4g}",
                            val=f"{val['total']:.4g}", refresh=False)
            if val["total"] < best:
                best, since = val["total"], 0
                best_state = copy.deepcopy(self.model.state_dict())
                self.history.best_epoch = epoch
            else:
                since += 1
                if patience and since >= patience:
                    self.history.stopped_early = True
                    break
        bar.close()
        if epoch not in snapshots:
            c = Collector(collector_max, seed=seed + epoch)
            self.evaluate(snap_data, c)
            snapshots[epoch] = c.arrays()
        if best_state is not None:
            self.model.load_state_dict(best_state)
        self.model.eval()
        return snapshots


@dataclass
class TrainResult:
    """What :func:`train` returns: the model (eval mode) and everything to describe it."""

    model: DualBranchMLP
    normalisation: Normalisation
    config: TrainConfig
    model_config: ModelConfig
    rows: dict[str, np.ndarray]  # dataset row indices of "train", "val", "test"
    history: History
    loss_table: dict[str, dict[str, float]]  # split -> {"mse", "kl", "total"} (Table 3)
    snapshots: dict[int, dict[str, np.ndarray]]  # epoch -> Collector.arrays()
    seconds: float  # wall time of the fit


def config_for(ds: Dataset, **overrides) -> ModelConfig:
    """The paper's architecture sized to the dataset's inputs, depths and bins."""
    return ModelConfig(**{"n_inputs": len(ds.space), "n_pressure": ds.pressure.shape[1],
                          "dist_shape": tuple(ds.histogram.shape[1:]), **overrides})


def make_split(ds: Dataset, cfg: TrainConfig) -> dict[str, np.ndarray]:
    """Dataset row indices of the 8:1:1 split of the trainable rows (seeded by ``cfg.seed``).

    Replicate rows (when trained on) are split by group: all runs at one parameter set land
    in the same part, so no test row shares its parameters with a training row.
    """
    rows = trainable_rows(ds, cfg.train_roles)
    units: dict[tuple, list[int]] = {}
    for i in rows:
        key = ("group", int(ds.group[i])) if ds.role[i] == "replicate" and ds.group[i] >= 0 \
            else ("row", int(i))
        units.setdefault(key, []).append(int(i))
    groups = list(units.values())
    parts = split_indices(len(groups), cfg.seed, cfg.split)
    return {name: np.sort(np.array([r for k in part for r in groups[k]], dtype=int))
            for name, part in zip(("train", "val", "test"), parts, strict=True)}


def fit_rows(ds: Dataset, train_rows: np.ndarray, val_rows: np.ndarray, cfg: TrainConfig,
             model_config: ModelConfig | None = None, norm: Normalisation | None = None,
             progress: bool = True, desc: str = "train"
             ) -> tuple[DualBranchMLP, Normalisation, Trainer, dict]:
    """Fit one model on given rows (used by :func:`train` and cross-validation).

    The normalisation is fitted on ``train_rows`` unless given. Returns (model, norm,
    trainer, snapshots).
    """
    model_config = model_config or config_for(ds)
    if len(train_rows) == 0:
        raise ConfigError("training rows", 0, "at least one row")
    norm = norm or Normalisation.fit(ds.pressure[train_rows])
    seed = int(cfg.seed) + 7919 * int(cfg.member)
    torch.manual_seed(seed)
    model = DualBranchMLP(model_config)
    train_data = SurrogateDataset(ds, norm, train_rows)
    val_data = SurrogateDataset(ds, norm, val_rows)
    loader = torch.utils.data.DataLoader(
        train_data, batch_size=cfg.batch_size, shuffle=True,
        generator=torch.Generator().manual_seed(seed))
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    trainer = Trainer(model, SurrogateLoss(cfg.mse_weight, cfg.kl_weight), opt,
                      progress=progress, desc=desc)
    snap_rows = np.concatenate([train_rows, val_rows])
    snapshots = trainer.fit(loader, val_data, cfg.epochs, cfg.patience,
                            tuple(cfg.snapshot_epochs), SurrogateDataset(ds, norm, snap_rows),
                            cfg.collector_max, seed)
    return model, norm, trainer, snapshots


def train(ds: Dataset, cfg: TrainConfig | None = None, model_config: ModelConfig | None = None,
          progress: bool = True, split: dict[str, np.ndarray] | None = None,
          norm: Normalisation | None = None) -> TrainResult:
    """Train one :class:`DualBranchMLP` on ``ds`` (see the module docstring).

    Args:
        ds: the dataset (physical parameters, pressure [Pa], histograms).
        cfg: training settings (defaults: the paper's 80 epochs, 8:1:1, weights 0.7/0.3).
        model_config: architecture (default: the paper's, sized by :func:`config_for`).
        progress: show a tqdm bar on stderr.
        split: row indices ``{"train", "val", "test"}`` to use instead of :func:`make_split`.
        norm: normalisation to use instead of fitting it on the training rows.

    Returns:
        A :class:`TrainResult`; ``loss_table`` holds eval-mode losses on each split.
    """
    cfg = cfg or TrainConfig()
    model_config = model_config or config_for(ds)
    if ds.pressure.shape[1] != model_config.n_pressure or \
            ds.histogram.shape[1:] != tuple(model_config.dist_shape) or \
            len(ds.space) != model_config.n_inputs:
        raise ConfigError("dataset shape", (len(ds.space), ds.pressure.shape[1],
                                            ds.histogram.shape[1:]),
                          f"({model_config.n_inputs}, {model_config.n_pressure}, "
                          f"{tuple(model_config.dist_shape)}) as in the model configuration")
    split = split or make_split(ds, cfg)
    t0 = time.perf_counter()
    model, norm, trainer, snapshots = fit_rows(
        ds, split["train"], split["val"], cfg, model_config, norm, progress,
        desc=f"member {cfg.member}" if cfg.member else "train")
    seconds = time.perf_counter() - t0
    table = {name: {**trainer.evaluate(SurrogateDataset(ds, norm, split[name])),
                    "n_rows": len(split[name])} for name in ("train", "val", "test")}
    return TrainResult(model=model, normalisation=norm, config=cfg, model_config=model_config,
                       rows={k: np.asarray(v) for k, v in split.items()},
                       history=trainer.history, loss_table=table, snapshots=snapshots,
                       seconds=seconds)


__all__ = ["PRESSURE_HEADS", "Collector", "History", "TrainConfig", "TrainResult", "Trainer",
           "config_for", "fit_rows", "make_split", "train"]

"""Two-phase projected optimisation of the eight unit parameters (paper section 2.4).

The parameters are one ``torch.nn.Parameter`` of shape (R, 8) in ``[0, 1]`` (R restarts
optimised together when batched, R = 1 otherwise). Starting points come from a scrambled,
seeded Sobol sequence over the free dimensions (:func:`sobol_starts`). Phase 1: Adam
(lr 0.05) for 30 % of the iterations; phase 2: L-BFGS (lr 0.01, strong-Wolfe line search,
one quasi-Newton iteration per step, the line search starting from the step lr and free to
extrapolate) for the other 70 %. Both phases step through closures;
after every update the parameters are projected back onto the cube (clamp) and fixed
parameters are reset to their held values. The closure evaluates the loss at the clamped
parameters, so the surrogate never sees a point outside ``[0, 1]`` (line-search trial points
included); the best point evaluated in a restart is kept, and the restart with the lowest loss
wins.

Beyond the paper, :func:`multistart` runs many Sobol-started restarts (default 64) as
batches and :func:`cluster_optima` groups the optima whose loss is within a tolerance of the
best, which shows at a glance whether the target pins the parameters down.

Restart batching (default): Adam acts elementwise, so a batch of restarts under Adam is
exactly R independent runs. L-BFGS on the summed loss of a batch (the restarts are
independent, so its Hessian is block-diagonal) shares one line search and one curvature history
between the restarts: not identical to separate runs, but each restart still converges to a
minimum of its own loss, and a batch of 3 costs about as much as one restart (the network's
cost per call is mostly overhead). ``batch=False`` runs the restarts one after the other, each
with its own L-BFGS (the paper's procedure to the letter; ~3x slower for 3 restarts).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from calendaring import ConfigError

ADAM_FRACTION = 0.3  # paper 2.4: Adam for ~30 % of the iterations
ADAM_LR = 0.05  # paper 2.4
LBFGS_LR = 0.01  # paper 2.4
DEFAULT_ITERATIONS = 500  # paper 3.2: 500 iterations
DEFAULT_RESTARTS = 3  # paper 3.2: three random restarts
DEFAULT_MULTISTART = 64


@dataclass(frozen=True)
class OptimiserConfig:
    """Settings of the two-phase optimiser (defaults: the paper's)."""

    iterations: int = DEFAULT_ITERATIONS
    restarts: int = DEFAULT_RESTARTS
    adam_fraction: float = ADAM_FRACTION
    adam_lr: float = ADAM_LR
    lbfgs_lr: float = LBFGS_LR
    lbfgs_history: int = 20
    line_search: str | None = "strong_wolfe"
    line_search_evals: int = 25  # most loss evaluations per line search
    seed: int = 0
    batch: bool | None = None  # None: batched (restarts > 1); False: one after the other
    batch_size: int = 64

    def __post_init__(self) -> None:
        if not (isinstance(self.iterations, int) and self.iterations >= 2):
            raise ConfigError("--iterations", self.iterations, "an integer >= 2")
        if not (isinstance(self.restarts, int) and self.restarts >= 1):
            raise ConfigError("--restarts", self.restarts, "an integer >= 1")
        if not 0.0 <= self.adam_fraction <= 1.0:
            raise ConfigError("adam_fraction", self.adam_fraction, "[0, 1]")
        for k in ("adam_lr", "lbfgs_lr"):
            if not getattr(self, k) > 0:
                raise ConfigError(k, getattr(self, k), "> 0")
        if self.line_search not in (None, "strong_wolfe"):
            raise ConfigError("line_search", self.line_search, "None or 'strong_wolfe'")
        if self.batch_size < 1:
            raise ConfigError("batch_size", self.batch_size, ">= 1")

    @property
    def n_adam(self) -> int:
        """Adam steps: ``round(adam_fraction x iterations)``."""
        return round(self.adam_fraction * self.iterations)

    @property
    def n_lbfgs(self) -> int:
        return self.iterations - self.n_adam

    @property
    def batched(self) -> bool:
        return self.restarts > 1 if self.batch is None else bool(self.batch)

    def to_json(self) -> dict:
        d = asdict(self)
        d.update(n_adam=self.n_adam, n_lbfgs=self.n_lbfgs, batched=self.batched)
        return d


# ---------------------------------------------------------------------- starts and fixing
def fixed_unit_values(space, fix: Mapping[str, float] | None) -> dict[int, float]:
    """``{name: physical value}`` -> ``{column: unit value}``, validated against the space
    (ConfigError naming the key, the value and the range)."""
    if not fix:
        return {}
    checked = space.check(dict(fix))
    row = space.from_dict(checked, default=space.reference)
    u = np.clip(space.to_unit(row), 0.0, 1.0)
    return {space.index(k): float(u[space.index(k)]) for k in checked}


def sobol_starts(n: int, dim: int, seed: int = 0, fixed: Mapping[int, float] | None = None
                 ) -> np.ndarray:
    """``n`` scrambled Sobol points in ``[0, 1]^dim`` (scipy, seeded); fixed columns set to
    their held values. Draws the next power of two and keeps the first ``n``."""
    from scipy.stats import qmc

    m = max(0, int(np.ceil(np.log2(max(n, 1)))))
    pts = qmc.Sobol(d=dim, scramble=True, seed=seed).random_base2(m)[:n]
    for j, v in (fixed or {}).items():
        pts[:, j] = v
    return pts


# ---------------------------------------------------------------------- one batch
@dataclass
class BatchResult:
    """Outcome of :func:`optimise_batch` for R restarts (unit parameters)."""

    start: np.ndarray  # (R, d)
    final: np.ndarray  # (R, d) last iterate
    best: np.ndarray  # (R, d) best evaluated point of each restart
    best_loss: np.ndarray  # (R,)
    final_loss: np.ndarray  # (R,)
    history: dict = field(default_factory=dict)  # phase, lr, loss (iterations, R), evals


def optimise_batch(loss_fn: Callable[[torch.Tensor], torch.Tensor], u0: np.ndarray,
                   free: np.ndarray, cfg: OptimiserConfig, progress=None) -> BatchResult:
    """Run the two phases on a batch of restarts.

    Args:
        loss_fn: (R, d) tensor in [0, 1] -> (R,) losses, differentiable.
        u0: (R, d) starting points in [0, 1] (held columns at their values).
        free: (d,) bool, the columns that move.
        cfg: optimiser settings.
        progress: a tqdm bar to advance by one per iteration, or None.
    """
    u0 = np.asarray(u0, float)
    free = np.asarray(free, bool)
    u = torch.nn.Parameter(torch.as_tensor(u0, dtype=torch.float32).clone())
    held = u.detach()[:, ~free].clone()
    held_cols = torch.as_tensor(np.nonzero(~free)[0])
    free_t = torch.as_tensor(free, dtype=torch.float32)
    u.register_hook(lambda g: g * free_t)  # fixed parameters get no gradient
    r = len(u0)
    best_loss = torch.full((r,), float("inf"))
    best = u.detach().clone()
    state = {"evals": 0, "last": None}

    def project() -> None:  # paper 2.4: clamp after every update
        with torch.no_grad():
            u.clamp_(0.0, 1.0)
            if len(held_cols):
                u[:, held_cols] = held

    def closure() -> torch.Tensor:
        opt.zero_grad()
        x = u.clamp(0.0, 1.0)  # the surrogate only ever sees points in the cube
        losses = loss_fn(x)
        total = losses.sum()
        total.backward()
        with torch.no_grad():
            lv = losses.detach()
            ok = torch.isfinite(lv) & (lv < best_loss)
            best_loss[ok] = lv[ok]
            best[ok] = x.detach()[ok]
        state["evals"] += 1
        if state["last"] is None:
            state["last"] = lv.clone()
        return total

    phase, lrs, trace = [], [], []
    project()
    opt = torch.optim.Adam([u], lr=cfg.adam_lr)
    for _ in range(cfg.n_adam):
        state["last"] = None
        opt.step(closure)
        project()
        phase.append("adam")
        lrs.append(opt.param_groups[0]["lr"])
        trace.append(state["last"].numpy().copy())
        if progress is not None:
            progress.update(1)
    # one quasi-Newton iteration per step; max_eval leaves the line search room to extrapolate
    # from lr (torch caps it at max_eval - 1 evaluations, and max_eval defaults to
    # 1.25 x max_iter)
    opt = torch.optim.LBFGS([u], lr=cfg.lbfgs_lr, max_iter=1, max_eval=1 + cfg.line_search_evals,
                            history_size=cfg.lbfgs_history, line_search_fn=cfg.line_search)
    for _ in range(cfg.n_lbfgs):
        state["last"] = None
        opt.step(closure)
        project()
        phase.append("lbfgs")
        lrs.append(opt.param_groups[0]["lr"])
        trace.append(state["last"].numpy().copy())
        if progress is not None:
            progress.update(1)
    with torch.no_grad():  # the final iterate counts too
        x = u.detach().clamp(0.0, 1.0)
        lv = loss_fn(x).detach()
        ok = torch.isfinite(lv) & (lv < best_loss)
        best_loss[ok] = lv[ok]
        best[ok] = x[ok]
    if not torch.isfinite(best_loss).all():
        raise FloatingPointError("the loss was never finite for some restart")
    return BatchResult(start=u0, final=x.double().numpy(), best=best.double().numpy(),
                       best_loss=best_loss.double().numpy(), final_loss=lv.double().numpy(),
                       history={"phase": phase, "lr": lrs, "loss": np.array(trace),
                                "evaluations": state["evals"]})


# ---------------------------------------------------------------------- restarts
@dataclass
class OptimisationResult:
    """Best unit parameters over all restarts and a record of every restart."""

    u: np.ndarray  # (d,) best unit parameters
    loss: float
    restarts: list[dict]  # start, best, loss, final_loss per restart (unit parameters)
    free: np.ndarray  # (d,) bool
    fixed: dict[int, float]  # column -> held unit value
    config: OptimiserConfig
    history: dict  # phase / lr / loss trace of the winning restart
    seconds: float
    evaluations: int

    @property
    def all_optima(self) -> np.ndarray:
        return np.array([r["best"] for r in self.restarts])

    @property
    def all_losses(self) -> np.ndarray:
        return np.array([r["loss"] for r in self.restarts])


def _bar(total: int, desc: str, progress: bool):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, file=sys.stderr, unit="it", leave=False,
                mininterval=0.5)


def calibrate(loss_fn: Callable[[torch.Tensor], torch.Tensor], dim: int,
              cfg: OptimiserConfig | None = None, fixed: Mapping[int, float] | None = None,
              progress: bool = False, starts: np.ndarray | None = None
              ) -> OptimisationResult:
    """Two-phase optimisation with ``cfg.restarts`` Sobol-started restarts; keeps the best.

    Args:
        loss_fn: (R, dim) tensor -> (R,) losses.
        dim: number of parameters.
        cfg: settings (paper defaults: 500 iterations x 3 restarts).
        fixed: ``{column: unit value}`` held parameters (see :func:`fixed_unit_values`).
        progress: show a tqdm bar on stderr.
        starts: (R, dim) explicit starting points instead of Sobol (held columns reset).
    """
    cfg = cfg or OptimiserConfig()
    fixed = dict(fixed or {})
    free = np.ones(dim, bool)
    for j in fixed:
        free[j] = False
    if starts is None:
        u0 = sobol_starts(cfg.restarts, dim, cfg.seed, fixed)
    else:
        u0 = np.array(starts, float).reshape(-1, dim)
        if not (np.all(np.isfinite(u0)) and u0.min() >= 0 and u0.max() <= 1):
            raise ConfigError("starts", "values", "finite unit parameters in [0, 1]")
        for j, v in fixed.items():
            u0[:, j] = v
    r = len(u0)
    t0 = time.perf_counter()
    chunks = ([np.arange(i, min(i + cfg.batch_size, r)) for i in range(0, r, cfg.batch_size)]
              if cfg.batched else [np.array([i]) for i in range(r)])
    bar = _bar(cfg.iterations * len(chunks), f"calibrate ({r} restart{'s' * (r > 1)})",
               progress)
    restarts: list[dict] = [{}] * r
    histories: dict[int, dict] = {}
    evals = 0
    try:
        for idx in chunks:
            res = optimise_batch(loss_fn, u0[idx], free, cfg, bar)
            evals += res.history["evaluations"]
            for k, i in enumerate(idx):
                restarts[i] = {"start": res.start[k].tolist(), "best": res.best[k].tolist(),
                               "loss": float(res.best_loss[k]),
                               "final_loss": float(res.final_loss[k])}
                histories[int(i)] = {"phase": res.history["phase"], "lr": res.history["lr"],
                                     "loss": res.history["loss"][:, k].tolist()}
    finally:
        if bar is not None:
            bar.close()
    losses = np.array([x["loss"] for x in restarts])
    k = int(np.argmin(losses))  # the restart with the lowest loss wins
    return OptimisationResult(u=np.array(restarts[k]["best"]), loss=float(losses[k]),
                              restarts=restarts, free=free, fixed=fixed, config=cfg,
                              history=histories[k], seconds=time.perf_counter() - t0,
                              evaluations=evals)


def multistart(loss_fn, dim: int, cfg: OptimiserConfig | None = None,
               fixed: Mapping[int, float] | None = None, progress: bool = False,
               restarts: int = DEFAULT_MULTISTART) -> OptimisationResult:
    """Many Sobol-started restarts (default 64), batched; see :func:`cluster_optima`."""
    cfg = cfg or OptimiserConfig()
    from dataclasses import replace

    cfg = replace(cfg, restarts=restarts, batch=True if cfg.batch is None else cfg.batch)
    return calibrate(loss_fn, dim, cfg, fixed=fixed, progress=progress)


# ---------------------------------------------------------------------- clustering
def cluster_optima(optima: np.ndarray, losses: np.ndarray, free: np.ndarray | None = None,
                   rtol: float = 0.05, atol: float = 1e-4, radius: float = 0.05) -> dict:
    """Group the optima whose loss is within ``best + atol + rtol |best|``.

    Complete-linkage clustering with the Chebyshev distance over the free columns (scipy):
    the members of one cluster differ by less than ``radius`` in every free unit parameter.

    Returns:
        ``{"tolerance": ..., "within": indices of the accepted optima (by loss),
        "clusters": [{"members", "size", "best_index", "best_loss", "centre", "lower",
        "upper"}, ...] by best loss}``; unit-parameter vectors as lists.
    """
    from scipy.cluster.hierarchy import fcluster, linkage

    x = np.asarray(optima, float)
    f = np.asarray(losses, float)
    free = np.ones(x.shape[1], bool) if free is None else np.asarray(free, bool)
    best = float(np.min(f))
    tol = atol + rtol * abs(best)
    within = np.nonzero(f <= best + tol)[0]
    within = within[np.argsort(f[within])]
    if len(within) == 1 or not free.any():
        labels = np.ones(len(within), int)
    else:
        z = linkage(x[within][:, free], method="complete", metric="chebyshev")
        labels = fcluster(z, t=radius, criterion="distance")
    clusters = []
    for lab in np.unique(labels):
        mem = within[labels == lab]
        b = mem[np.argmin(f[mem])]
        clusters.append({"members": mem.tolist(), "size": len(mem), "best_index": int(b),
                         "best_loss": float(f[b]), "centre": x[mem].mean(axis=0).tolist(),
                         "lower": x[mem].min(axis=0).tolist(),
                         "upper": x[mem].max(axis=0).tolist()})
    clusters.sort(key=lambda c: c["best_loss"])
    return {"tolerance": {"rtol": rtol, "atol": atol, "radius_unit": radius,
                          "loss_threshold": best + tol},
            "within": within.tolist(), "clusters": clusters}


__all__ = ["ADAM_FRACTION", "ADAM_LR", "DEFAULT_ITERATIONS", "DEFAULT_MULTISTART",
           "DEFAULT_RESTARTS", "LBFGS_LR", "BatchResult", "OptimisationResult",
           "OptimiserConfig", "calibrate", "cluster_optima", "fixed_unit_values",
           "multistart", "optimise_batch", "sobol_starts"]

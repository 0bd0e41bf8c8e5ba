"""Identifiability at the optimum: Hessian eigen-spectrum and loss profiles.

* :func:`hessian_spectrum`: the Hessian of the data part of the loss (pressure + centroid
  terms, without the boundary barrier, which would make every direction look curved) with
  respect to the free unit parameters, by ``torch.autograd.functional.hessian``; eigenvalues,
  eigenvectors and the parameters that dominate each eigen-direction. A direction whose
  eigenvalue is tiny relative to the largest is one the target cannot constrain ("sloppy").
* :func:`loss_profiles`: the loss along each free parameter over ``[0, 1]``, either as a slice
  (the others held at the optimum) or as a profile (the others re-optimised at each grid
  value with a short two-phase run, batched over the grid).

A parameter whose profile stays within ``flat_tol`` of the minimum over the whole range is
reported as not identifiable from this target. The paper's Sobol analysis leads one to expect
this of gamma and R_t.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from inverse.loss import CompositeLoss, weights_frozen
from inverse.optimise import OptimiserConfig, optimise_batch

SLOPPY_RATIO = 1e-3  # eigenvalue / largest below which a direction is called sloppy


def data_loss(loss: CompositeLoss, u: torch.Tensor) -> torch.Tensor:
    """The weighted pressure + centroid terms, (n,)."""
    t = loss.terms(u)
    out = loss.weights["pressure"] * t["pressure"]
    if "centroid" in t:
        out = out + loss.weights["centroid"] * t["centroid"]
    return out


def hessian_spectrum(loss: CompositeLoss, u_opt: np.ndarray, free: np.ndarray,
                     names: list[str]) -> dict:
    """Eigen-decomposition of the data-loss Hessian over the free unit parameters at ``u_opt``.

    Returns a dict: ``parameters`` (free names), ``hessian`` (k x k), ``eigenvalues``
    (descending), ``eigenvectors`` (columns, same order), ``directions`` (per eigenvalue: its
    relative size and the parameters with |component| > 0.3), ``condition_number`` and
    ``sloppy`` (directions with eigenvalue < 1e-3 x the largest).
    """
    free = np.asarray(free, bool)
    base = torch.as_tensor(np.asarray(u_opt, float), dtype=torch.float32)
    idx = torch.as_tensor(np.nonzero(free)[0])
    free_names = [n for n, f in zip(names, free, strict=True) if f]

    def f(v: torch.Tensor) -> torch.Tensor:
        u = base.clone().index_put((idx,), v)
        return data_loss(loss, u[None, :])[0]

    h = torch.autograd.functional.hessian(f, base[idx].clone()).double().numpy()
    h = 0.5 * (h + h.T)
    w, v = np.linalg.eigh(h)
    order = np.argsort(w)[::-1]
    w, v = w[order], v[:, order]
    top = max(float(w[0]), 1e-300)
    directions = []
    for k in range(len(w)):
        comp = v[:, k] * np.sign(v[np.argmax(np.abs(v[:, k])), k])
        directions.append({
            "eigenvalue": float(w[k]), "relative": float(w[k] / top),
            "dominant": {free_names[i]: round(float(comp[i]), 3)
                         for i in np.argsort(-np.abs(comp)) if abs(comp[i]) > 0.3}})
    pos = w[w > 0]
    return {"parameters": free_names, "hessian": h.tolist(), "eigenvalues": w.tolist(),
            "eigenvectors": v.tolist(), "directions": directions,
            "condition_number": float(pos[0] / pos[-1]) if len(pos) == len(w) else float("inf"),
            "sloppy": [d for d in directions if d["relative"] < SLOPPY_RATIO],
            "note": "Hessian of the weighted pressure + centroid terms w.r.t. unit parameters"}


def loss_profiles(loss: CompositeLoss, u_opt: np.ndarray, free: np.ndarray, names: list[str],
                  points: int = 21, mode: str = "slice", iterations: int = 60,
                  flat_tol: float = 0.1, atol: float = 1e-4) -> dict:
    """Loss along each free parameter over ``[0, 1]`` (``points`` values).

    Args:
        mode: ``"slice"`` (others held at the optimum) or ``"optimised"`` (others re-fitted
            with ``iterations`` two-phase steps from the optimum, batched over the grid).
        flat_tol: a profile whose rise above its minimum stays below ``flat_tol x best +
            atol`` everywhere is reported as flat (not identifiable).
    Returns:
        ``{"mode", "grid_unit", "profiles": {name: {"loss": [...], "rise": max - min,
        "flat": bool, "argmin_unit": ...}}, "flat": [names]}``.
    """
    if mode not in ("slice", "optimised"):
        from calendaring import ConfigError

        raise ConfigError("profile mode", mode, "'slice' or 'optimised'")
    free = np.asarray(free, bool)
    grid = np.linspace(0.0, 1.0, points)
    u_opt = np.asarray(u_opt, float)
    best = float(loss.evaluate(u_opt)["total"][0])
    out = {}
    for j in np.nonzero(free)[0]:
        rows = np.repeat(u_opt[None, :], points, axis=0)
        rows[:, j] = grid
        if mode == "slice":
            vals = loss.evaluate(rows)["total"]
        else:
            f2 = free.copy()
            f2[j] = False
            cfg = replace(OptimiserConfig(iterations=iterations), restarts=points, batch=True)
            vals = optimise_batch(loss, rows, f2, cfg).best_loss
        rise = float(vals.max() - min(vals.min(), best))
        out[names[j]] = {"loss": vals.tolist(), "rise": rise,
                         "flat": bool(rise < flat_tol * abs(best) + atol),
                         "argmin_unit": float(grid[int(np.argmin(vals))])}
    return {"mode": mode, "grid_unit": grid.tolist(), "best_loss": best, "profiles": out,
            "flat": [n for n, p in out.items() if p["flat"]],
            "flat_rule": f"rise < {flat_tol} x best loss + {atol}"}


def plot_identifiability(report: dict, path, symbols: dict[str, str] | None = None):
    """Profiles (one panel per free parameter) and the eigen-spectrum, one PNG."""
    import matplotlib.pyplot as plt

    prof = report["profiles"]
    names = list(prof["profiles"])
    symbols = symbols or {}
    n = len(names) + 1
    cols = min(3, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.8 * rows), squeeze=False)
    grid = prof["grid_unit"]
    for ax, name in zip(axes.flat, names, strict=False):
        p = prof["profiles"][name]
        ax.plot(grid, p["loss"], "o-", ms=3)
        ax.axvline(report["u_opt"][report["names"].index(name)], color="k", lw=0.8, ls="--")
        ax.set_yscale("log")
        ax.set_xlabel(f"{symbols.get(name, name)} (unit)")
        ax.set_title(f"{symbols.get(name, name)}" + (" (flat)" if p["flat"] else ""),
                     fontsize=9)
    ax = axes.flat[len(names)]
    ev = np.clip(np.array(report["hessian"]["eigenvalues"]), 1e-300, None)
    ax.semilogy(np.arange(1, len(ev) + 1), ev, "s-")
    ax.set_xlabel("eigenvalue rank")
    ax.set_title("Hessian eigen-spectrum", fontsize=9)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.suptitle(f"loss {prof['mode']} profiles", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def identifiability_report(loss: CompositeLoss, u_opt: np.ndarray, free: np.ndarray,
                           names: list[str], profile_mode: str = "slice",
                           points: int = 21) -> dict:
    """Hessian spectrum and profiles together (surrogate weights frozen meanwhile)."""
    with weights_frozen(loss.model):
        return _report(loss, u_opt, free, names, profile_mode, points)


def _report(loss, u_opt, free, names, profile_mode, points) -> dict:
    return {"u_opt": np.asarray(u_opt, float).tolist(), "names": list(names),
            "hessian": hessian_spectrum(loss, u_opt, free, names),
            "profiles": loss_profiles(loss, u_opt, free, names, points=points,
                                      mode=profile_mode)}


__all__ = ["SLOPPY_RATIO", "data_loss", "hessian_spectrum", "identifiability_report",
           "loss_profiles", "plot_identifiability"]

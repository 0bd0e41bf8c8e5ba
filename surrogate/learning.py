"""Learning curve: the surrogate's error on the held-out seed means against the number of
training runs, and how many runs a target takes.

For each repeat ``r`` the trainable rows are shuffled once (seed ``cfg.seed + r``) and the
first ``n`` of them train a model for each size ``n`` (nested subsets, so the curve of one
repeat is not blurred by a different draw at each size): one ninth of them (at least one)
is the validation slice of early stopping, as in cross-validation, and the normalisation is
fitted on the rest. Every model is scored by :func:`surrogate.evaluate.seed_mean_comparison`
against the seed means of the ``holdout`` groups, never trained on.

The target size: the smallest measured size whose mean pressure MSE (normalised units)
meets the target, else the size where a fit ``MSE(n) = c + a n^-b`` crosses it (an
extrapolation, marked as such), else none when the fitted floor ``c`` is at or above the
target. The floor the seed means themselves impose (``pressure_mse_normalised_floor``) is
reported with it: no model can go below it on average.

Resumable: ``learning_curve.json`` in the output folder is rewritten after every fit, and a
rerun on the same dataset with the same training settings skips the fits already recorded
(more sizes or repeats add to them; other settings need another folder).

    surrogate learning-curve data/rve.h5 --sizes 35 70 140 280 --repeats 3 --out-dir lc/
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from calendaring import ConfigError, Dataset, save_figure, seed_means
from surrogate.api import SurrogateModel
from surrogate.data import trainable_rows
from surrogate.evaluate import PAPER_TABLE3, seed_mean_comparison, write_json
from surrogate.model import ModelConfig
from surrogate.train import TrainConfig, fit_rows

RESULT = "learning_curve.json"
FIGURE = "learning_curve.png"


def default_sizes(n_rows: int, n_sizes: int = 4, smallest: int = 10) -> list[int]:
    """Halvings of ``n_rows`` (``n_rows``, ``n_rows / 2``, ...), at most ``n_sizes`` of them
    and none below ``smallest``, ascending."""
    sizes = sorted({round(n_rows / 2**k) for k in range(n_sizes)
                    if n_rows / 2**k >= smallest})
    return sizes or [int(n_rows)]


def power_law_fit(n, mse) -> dict | None:
    """Least-squares fit of ``mse = c + a n^-b`` (a, c >= 0; 0 < b <= 3) in log space;
    None with fewer than three sizes or when the fit fails."""
    from scipy.optimize import least_squares

    n = np.asarray(n, float)
    y = np.asarray(mse, float)
    if len(n) < 3 or np.any(y <= 0):
        return None

    def resid(t):
        a, b, c = np.exp(t[0]), t[1], np.exp(t[2])
        return np.log(c + a * n**-b) - np.log(y)

    fit = None
    for b0 in (0.25, 0.5, 1.0, 2.0):  # a few starts: the log-space problem is not convex
        for c0 in (y.min() / 100, y.min() / 2):
            start = [np.log(max(y[0] * n[0] ** b0, 1e-30)), b0, np.log(max(c0, 1e-30))]
            try:
                f = least_squares(resid, start, bounds=([-np.inf, 1e-3, -np.inf],
                                                        [np.inf, 3, np.inf]),
                                  xtol=1e-12, ftol=1e-12, gtol=1e-12)
            except (ValueError, FloatingPointError):
                continue
            if f.success and (fit is None or f.cost < fit.cost):
                fit = f
    if fit is None:
        return None
    a, b, c = float(np.exp(fit.x[0])), float(fit.x[1]), float(np.exp(fit.x[2]))
    return {"a": a, "b": b, "c": c,
            "rms_log_residual": float(np.sqrt(np.mean(fit.fun**2)))}


def runs_for_target(sizes, mse_mean, target: float, fit: dict | None) -> dict:
    """How many training runs the pressure-MSE ``target`` takes (see the module docstring)."""
    for n, m in zip(sizes, mse_mean, strict=True):
        if m <= target:
            return {"runs": int(n), "how": "measured"}
    if fit is None:
        return {"runs": None, "how": "no fit (fewer than 3 sizes)"}
    if fit["c"] >= target:
        return {"runs": None, "how": f"not reachable: the fitted floor c = {fit['c']:.3g} is "
                                     f"at or above the target {target:g}"}
    n = (fit["a"] / (target - fit["c"])) ** (1 / fit["b"])
    return {"runs": int(np.ceil(n)), "how": "extrapolated from the power-law fit"}


def _request(ds: Dataset, cfg: TrainConfig, model_config: ModelConfig) -> dict:
    """What makes two fits of one (repeat, size) the same fit."""
    req = {"dataset_fingerprint": ds.fingerprint, "train_config": cfg.to_dict(),
           "model_config": model_config.to_dict()}
    return json.loads(json.dumps(req, default=list))  # as it reads back from the file


def learning_curve(ds: Dataset, sizes=None, repeats: int = 1, cfg: TrainConfig | None = None,
                   model_config: ModelConfig | None = None, out_dir: str | Path | None = None,
                   target: float = PAPER_TABLE3["test"]["mse"], kl_simulations: int = 200,
                   progress: bool = True) -> dict:
    """Train on nested subsets of the trainable rows and score each model on the held-out
    seed means (see the module docstring).

    Args:
        ds: the dataset; needs ``holdout`` groups of >= 2 seeds.
        sizes: training-run counts (default :func:`default_sizes`); each <= the trainable rows.
        repeats: shuffles of the trainable rows (the spread of each point).
        cfg: training settings (``seed`` seeds the shuffles; ``train_roles`` the rows).
        model_config: architecture (default: the paper's, sized to the dataset).
        out_dir: where ``learning_curve.json`` and the figure go (resumed when present).
        target: the pressure MSE target, normalised units (default: the paper's Table 3).
        kl_simulations: draws of the perfect-model KL (:func:`perfect_model_kl`).
        progress: a tqdm bar on stderr.
    """
    from surrogate.gp import fit_pressure_gp
    from surrogate.train import config_for

    cfg = cfg or TrainConfig()
    model_config = model_config or config_for(ds)
    n_groups = len(seed_means(ds, "holdout"))
    if n_groups == 0:
        raise ConfigError("dataset", str(ds.path or "<memory>"),
                          "holdout groups of >= 2 seeds (the learning curve's test targets)")
    rows = trainable_rows(ds, cfg.train_roles)
    sizes = sorted({int(s) for s in (sizes or default_sizes(len(rows)))})
    if repeats < 1:
        raise ConfigError("--repeats", repeats, "an integer >= 1")
    for s in sizes:
        if not 3 <= s <= len(rows):
            raise ConfigError("--sizes", s, f"3 to {len(rows)} (the trainable rows)")
    request = _request(ds, cfg, model_config)
    out_dir = Path(out_dir) if out_dir is not None else None
    points: list[dict] = []
    if out_dir is not None and (out_dir / RESULT).is_file():
        old = json.loads((out_dir / RESULT).read_text())
        if old.get("request") != request:
            raise ConfigError("--out-dir", str(out_dir), "a new folder, or one holding a "
                              "learning curve of the same dataset and training settings "
                              "(its fits are reused)")
        points = old.get("points", [])
    done = {(p["repeat"], p["n"]) for p in points}
    todo = [(r, n) for r in range(repeats) for n in sizes if (r, n) not in done]
    bar = tqdm(todo, desc="learning curve", file=sys.stderr, disable=not progress, unit="fit")
    for r, n in bar:
        perm = np.random.default_rng(cfg.seed + r).permutation(rows)
        use = perm[:n]
        n_val = max(1, round(n / 9))
        val, fit = np.sort(use[:n_val]), np.sort(use[n_val:])
        t0 = time.perf_counter()
        net, norm, trainer, _ = fit_rows(ds, fit, val, replace(cfg, snapshot_epochs=()),
                                         model_config, progress=False)
        gp = None
        if cfg.pressure_head == "gp":
            gp, _ = fit_pressure_gp(ds.unit_params[use], norm.normalise(ds.pressure[use]),
                                    cfg.gp_components, cfg.seed)
        sm = SurrogateModel([net], norm, ds.space, ds.depth, ds.load_edges, ds.diameter_edges,
                            ds.load_scale, {"train_config": cfg.to_dict()}, pressure_gp=gp)
        h = seed_mean_comparison(sm, ds, kl_simulations=kl_simulations)
        p = h["metrics"]["pressure"]
        points.append({
            "repeat": r, "n": n, "n_fit": len(fit), "n_val": len(val),
            "fit_seconds": time.perf_counter() - t0,
            "best_epoch": trainer.history.best_epoch,
            "pressure_mse_normalised": h["pressure_mse_normalised"],
            "pressure_rmse_Pa": p["pressure_rmse_Pa"],
            "abs_error_Pa_at_stroke": {k: v["abs_error_Pa"] for k, v in p["at_stroke"].items()},
            "kl_mean": h["kl_model"], "kl_perfect": h["kl_perfect"],
            "pressure_mse_normalised_floor": h["pressure_mse_normalised_floor"]})
        bar.set_postfix(n=n, mse=f"{h['pressure_mse_normalised']:.3g}")
        if out_dir is not None:
            write_json(out_dir / RESULT, {"request": request, "points": points})
    out = summarise([p for p in points if p["repeat"] < repeats and p["n"] in sizes],
                    sizes, target)
    out.update({"request": request, "points": points, "holdout_groups": n_groups,
                "trainable_rows": len(rows), "requested": {"sizes": sizes, "repeats": repeats}})
    if out_dir is not None:
        write_json(out_dir / RESULT, out)
        if learning_curve_figure(out, out_dir / FIGURE):
            out["files"] = [RESULT, FIGURE]
            write_json(out_dir / RESULT, out)
    return out


def summarise(points: list[dict], sizes, target: float) -> dict:
    """Per-size mean and sd over repeats, the power-law fit and the runs the target takes."""
    per = []
    for n in sizes:
        pts = [p for p in points if p["n"] == n]
        mse = np.array([p["pressure_mse_normalised"] for p in pts])
        kl = np.array([p["kl_mean"] for p in pts if p["kl_mean"] is not None])
        kp = [p["kl_perfect"] for p in pts if p["kl_perfect"] is not None]
        per.append({"n": int(n), "repeats": len(pts),
                    "pressure_mse_normalised_mean": float(mse.mean()),
                    "pressure_mse_normalised_sd": float(mse.std(ddof=1)) if len(mse) > 1
                    else None,
                    "abs_error_MPa_at_stroke_mean": {
                        k: float(np.mean([p["abs_error_Pa_at_stroke"][k] for p in pts]) / 1e6)
                        for k in pts[0]["abs_error_Pa_at_stroke"]},
                    "kl_mean": float(kl.mean()) if len(kl) else None,
                    "kl_sd": float(kl.std(ddof=1)) if len(kl) > 1 else None,
                    "kl_perfect": float(np.mean(kp)) if kp else None})
    mse_mean = [s["pressure_mse_normalised_mean"] for s in per]
    fit = power_law_fit(sizes, mse_mean)
    return {"target_pressure_mse_normalised": target, "sizes": per, "power_law": fit,
            "runs_for_target": runs_for_target(sizes, mse_mean, target, fit),
            "pressure_mse_normalised_floor": points[0]["pressure_mse_normalised_floor"]
            if points else None,
            "units": {"pressure_mse_normalised": "normalised cube-root units (1)",
                      "abs_error_MPa_at_stroke_mean": "MPa (reading units)",
                      "kl": "nat", "_Pa": "Pa"}}


def learning_curve_figure(out: dict, path: str | Path) -> Path | None:
    """Pressure MSE and KL against training runs (log-log), with the target, the seed-mean
    floor, the power-law fit and the perfect-model KL."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullFormatter

    per = out["sizes"]
    if not per:
        return None
    n = np.array([s["n"] for s in per], float)
    fig = Figure(figsize=(9, 3.6), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    req = out.get("requested", {})
    shown = [p for p in out["points"] if p["n"] in req.get("sizes", [p["n"]])
             and p["repeat"] < req.get("repeats", p["repeat"] + 1)]
    for p in shown:
        ax1.plot(p["n"], p["pressure_mse_normalised"], ".", color="0.6")
        if p["kl_mean"] is not None:
            ax2.plot(p["n"], p["kl_mean"], ".", color="0.6")
    head = out.get("request", {}).get("train_config", {}).get("pressure_head", "mlp")
    ax1.plot(n, [s["pressure_mse_normalised_mean"] for s in per], "o-",
             label=f"{'GP pressure head' if head == 'gp' else 'MLP'} (mean)")
    fit = out.get("power_law")
    if fit:
        nn = np.geomspace(n.min(), max(n.max(), (out["runs_for_target"]["runs"] or 0)), 100)
        ax1.plot(nn, fit["c"] + fit["a"] * nn ** -fit["b"], "--", color="tab:blue", lw=1,
                 label=f"fit c + a n^-{fit['b']:.2f}")
    ax1.axhline(out["target_pressure_mse_normalised"], color="tab:red", lw=1, label="target")
    if out.get("pressure_mse_normalised_floor"):
        ax1.axhline(out["pressure_mse_normalised_floor"], color="k", ls=":", lw=1,
                    label="exact mean curve")
    ax1.set(xscale="log", yscale="log", xlabel="training runs",
            ylabel="pressure MSE, held-out seed means")
    ax1.legend(fontsize=8)
    kl = [s["kl_mean"] for s in per]
    if any(k is not None for k in kl):
        ax2.plot(n, [np.nan if k is None else k for k in kl], "o-",
                 label="network (mean)" if head == "gp" else "MLP (mean)")
        kp = [s["kl_perfect"] for s in per if s["kl_perfect"] is not None]
        if kp:
            ax2.axhline(float(np.mean(kp)), color="k", ls=":", lw=1, label="perfect model")
        ax2.set(xscale="log", yscale="log", xlabel="training runs",
                ylabel="KL(pooled seeds || predicted)")
        ax2.legend(fontsize=8)
    for ax in fig.axes:  # the training sizes as plain numbers, no crowded minor labels
        ax.set_xticks(n, [f"{int(v)}" for v in n])
        ax.xaxis.set_minor_formatter(NullFormatter())
    return save_figure(fig, path, dpi=120)


def format_learning_curve(out: dict) -> list[str]:
    """Printed table (MPa for reading; the JSON stays SI)."""
    lines = [f"learning curve on {out['holdout_groups']} held-out seed means "
             f"(exact mean curve: MSE {out['pressure_mse_normalised_floor']:.3g}):",
             "| runs | pressure MSE (normalised) | abs. error at 25/50/75/100 % (MPa) | KL | "
             "perfect-model KL |", "|---|---|---|---|---|"]

    def pm(m, s):
        return f"{m:.3g}" + (f" +- {s:.2g}" if s is not None else "")

    for s in out["sizes"]:
        at = " / ".join(f"{v:.3g}" for v in s["abs_error_MPa_at_stroke_mean"].values())
        kl = "n/a" if s["kl_mean"] is None else pm(s["kl_mean"], s["kl_sd"])
        kp = "n/a" if s["kl_perfect"] is None else f"{s['kl_perfect']:.3g}"
        mse = pm(s["pressure_mse_normalised_mean"], s["pressure_mse_normalised_sd"])
        lines.append(f"| {s['n']} | {mse} | {at} | {kl} | {kp} |")
    fit, t = out.get("power_law"), out["runs_for_target"]
    if fit:
        lines.append(f"fit: MSE = {fit['c']:.3g} + {fit['a']:.3g} n^-{fit['b']:.3f}")
    lines.append(f"target MSE {out['target_pressure_mse_normalised']:g}: "
                 + (f"{t['runs']} runs ({t['how']})" if t["runs"] else t["how"]))
    return lines


__all__ = ["default_sizes", "format_learning_curve", "learning_curve", "learning_curve_figure",
           "power_law_fit", "runs_for_target", "summarise"]

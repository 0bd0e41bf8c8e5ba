"""Honest validation of a surrogate: errors in several units, noise floors, CV, baseline.

:func:`evaluate` runs everything on a model and a dataset and writes the outputs:

- the test split of the training run (recovered by run id when the dataset is the one the
  model was trained on, checked by fingerprint), the ``holdout`` rows and, when the dataset
  differs, every ``train`` row: pressure MSE in the paper's normalised cube-root units
  (the model's own normalisation), MSE / RMSE / MAE in Pa, relative error at 25/50/75/100 %
  of the stroke; distribution KL (1e-8 floor) and centroid errors
  (:func:`calendaring.data.dataset.centroids`); ensemble spread and 2-sigma coverage;
- the held-out seed means (the test targets at the representative volume): errors against
  the mean of each ``holdout`` group's seeds, next to the MSE the exact mean curve would
  score and the KL a model of the true distribution would score
  (:func:`seed_mean_comparison`);
- the replicate groups: model error against each replicate next to the run-to-run noise
  floor (:func:`calendaring.data.dataset.noise_floor`; the pressure floor recomputed in the
  model's normalisation), with their ratios;
- the PCA + GP baseline (:mod:`surrogate.baseline`) on the same rows;
- repeated K-fold cross-validation of the MLP and the baseline (normalisation refitted on
  each training fold, early stopping on a validation slice of it);
- Table 3 (loss per branch and split) as JSON and markdown, the Fig. 5 PCA convergence
  figure, the loss histories and example pressure curves as PNG.

Files hold SI units (keys name them: ``_Pa``, ``_m``); MPa and micrometres appear only in
the figures and the markdown table.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from calendaring import (
    ConfigError,
    Dataset,
    centroids,
    kl_divergence,
    noise_floor,
    perfect_model_kl,
    save_figure,
    seed_means,
    write_text,
)
from surrogate.api import SurrogateModel
from surrogate.baseline import PCAGPBaseline
from surrogate.checkpoint import json_default
from surrogate.data import has_events, trainable_rows
from surrogate.losses import KL_WEIGHT, MSE_WEIGHT
from surrogate.model import ModelConfig
from surrogate.train import TrainConfig, fit_rows

STROKE_FRACTIONS = (0.25, 0.5, 0.75, 1.0)
PAPER_TABLE3 = {"train": {"mse": 0.0018, "kl": 0.3000, "total": 0.0913},
                "val": {"mse": 0.0011, "kl": 0.3689, "total": 0.1114},
                "test": {"mse": 0.0003, "kl": 0.3300, "total": 0.0992}}
KL_PERFECT_FACTOR = 1.1
"""Target: the KL against held-out seed means within this multiple of what a model that
predicts the true distribution would score (:func:`seed_mean_comparison`)."""


# ---------------------------------------------------------------------- file helpers
def write_json(path: str | Path, obj) -> Path:
    return write_text(path, json.dumps(obj, indent=2, default=json_default) + "\n")


def _save_figure(fig, path: str | Path) -> Path:
    return save_figure(fig, path, dpi=120)


# ---------------------------------------------------------------------- metrics
def stroke_index(n_points: int, fraction: float) -> int:
    """Index of the pressure point at ``fraction`` of the stroke (as in ``noise_floor``)."""
    return min(n_points - 1, max(0, round(fraction * n_points) - 1))


def pressure_errors(p_true: np.ndarray, p_pred: np.ndarray, model: SurrogateModel) -> dict:
    """Pressure errors of ``(n, 196)`` curves [Pa]: normalised MSE (the paper's unit, the
    model's normalisation), MSE [Pa^2], RMSE and MAE [Pa], and at 25/50/75/100 % of the
    stroke the mean absolute error [Pa] and the mean / median relative error."""
    p_true = np.asarray(p_true, float)
    p_pred = np.asarray(p_pred, float)
    x_true, x_pred = model.normalise_pressure(p_true), model.normalise_pressure(p_pred)
    err = p_pred - p_true
    out = {"n_rows": len(p_true),
           "pressure_mse_normalised": float(np.mean((x_pred - x_true) ** 2)),
           "pressure_mse_Pa2": float(np.mean(err**2)),
           "pressure_rmse_Pa": float(np.sqrt(np.mean(err**2))),
           "pressure_mae_Pa": float(np.mean(np.abs(err))),
           "at_stroke": {}}
    for f in STROKE_FRACTIONS:
        j = stroke_index(p_true.shape[1], f)
        ok = p_true[:, j] > 0
        rel = np.abs(err[ok, j]) / p_true[ok, j]
        out["at_stroke"][f"{round(f * 100)}%"] = {
            "depth_m": float(model.depth[j]),
            "abs_error_Pa": float(np.mean(np.abs(err[:, j]))),
            "rel_error_mean": float(rel.mean()) if rel.size else None,
            "rel_error_median": float(np.median(rel)) if rel.size else None}
    return out


def distribution_errors(d_true: np.ndarray, d_pred: np.ndarray, model: SurrogateModel) -> dict:
    """KL(true || predicted) with the 1e-8 floor, and centroid errors: load (relative; the
    centroid is geometric on a log axis) and diameter (absolute [m] and relative)."""
    if len(d_true) == 0:
        return {"n_rows": 0}
    kl = kl_divergence(d_true, d_pred)
    log_load = model.load_scale == "log"
    ct = centroids(d_true, model.load_centres, model.diameter_centres, log_load)
    cp = centroids(d_pred, model.load_centres, model.diameter_centres, log_load)
    load_rel = np.abs(cp[:, 0] - ct[:, 0]) / ct[:, 0]
    dia_abs = np.abs(cp[:, 1] - ct[:, 1])
    return {"n_rows": len(d_true), "kl_mean": float(kl.mean()), "kl_median": float(np.median(kl)),
            "kl_max": float(kl.max()),
            "centroid_load_rel_error_mean": float(np.nanmean(load_rel)),
            "centroid_diameter_abs_error_m_mean": float(np.nanmean(dia_abs)),
            "centroid_diameter_rel_error_mean": float(np.nanmean(dia_abs / ct[:, 1]))}


def model_metrics(model: SurrogateModel, ds: Dataset, rows, pred=None) -> dict:
    """All errors of ``model`` on dataset ``rows`` (see :func:`pressure_errors`,
    :func:`distribution_errors`); ensembles add spread and 2-sigma coverage. ``pred``: the
    model's prediction for those rows, if already made."""
    rows = np.asarray(rows, dtype=int)
    if len(rows) == 0:
        return {"n_rows": 0}
    sub = ds.subset(rows)
    pred = pred or model.predict_unit(sub.unit_params)
    out = {"pressure": pressure_errors(sub.pressure, pred.pressure, model)}
    ev = has_events(sub)
    out["distribution"] = distribution_errors(sub.histogram[ev], pred.distribution[ev], model)
    out["loss"] = loss_terms(model, sub, pred)
    if pred.pressure_normalised_var is not None:
        sd = np.sqrt(pred.pressure_normalised_var)
        err = np.abs(pred.pressure_normalised - model.normalise_pressure(sub.pressure))
        out["ensemble"] = {"pressure_std_normalised_mean": float(sd.mean()),
                           "pressure_std_Pa_mean": float(pred.pressure_std.mean()),
                           "coverage_2sigma": float(np.mean(err <= 2 * sd)),
                           "source": "GP latent variance"
                           if getattr(model, "pressure_gp", None) is not None
                           else "member spread"}
    return out


def loss_terms(model: SurrogateModel, sub: Dataset, pred=None) -> dict:
    """The training loss terms (MSE, KL, 0.7 MSE + 0.3 KL) of ``model`` on ``sub``."""
    pred = pred or model.predict_unit(sub.unit_params)
    mse = float(np.mean((pred.pressure_normalised - model.normalise_pressure(sub.pressure)) ** 2))
    ev = has_events(sub)
    kl = float(np.mean(kl_divergence(sub.histogram[ev], pred.distribution[ev]))) \
        if ev.any() else float("nan")
    w = model.info.get("train_config", {})
    wm, wk = w.get("mse_weight", MSE_WEIGHT), w.get("kl_weight", KL_WEIGHT)
    return {"mse": mse, "kl": kl, "total": wm * mse + wk * kl, "n_rows": len(sub)}


def replicate_comparison(model: SurrogateModel, ds: Dataset) -> dict | None:
    """Model error on the replicate groups next to their run-to-run noise floor.

    Pressure: the model's normalised MSE against each replicate, and the floor (mean
    per-point replicate variance, ddof 1, in the model's normalisation: what a perfect mean
    predictor scores, times n/(n-1)). Distribution: mean KL(replicate || prediction) and
    the floor mean KL(replicate || group's pooled histogram) from
    :func:`calendaring.data.dataset.noise_floor`, with ``kl_perfect_model_ratio``: the multiple
    of that floor a model predicting the true distribution would score (events drawn
    independently; :func:`calendaring.data.dataset.sampled_kl_floor`). None without a group of
    >= 2 runs.
    """
    groups = [g for g in sorted(set(int(g) for g in ds.group if g >= 0))
              if np.sum(ds.group == g) >= 2]
    if not groups:
        return None
    floor = noise_floor(ds)
    mse_model, mse_floor, kl_model = [], [], []
    for g in groups:
        idx = np.nonzero(ds.group == g)[0]
        x = model.normalise_pressure(ds.pressure[idx])
        pred = model.predict_unit(ds.unit_params[idx[:1]])
        mse_model.append(float(np.mean((x - pred.pressure_normalised) ** 2)))
        mse_floor.append(float(x.var(axis=0, ddof=1).mean()))
        ev = idx[ds.n_events[idx] > 0]
        if len(ev):
            kl_model.append(float(np.mean(kl_divergence(ds.histogram[ev], pred.distribution))))
    out = {"groups": len(groups), "runs": int(np.isin(ds.group, groups).sum()),
           "pressure_mse_normalised_model": float(np.mean(mse_model)),
           "pressure_mse_normalised_floor": float(np.mean(mse_floor)),
           "kl_model": float(np.mean(kl_model)) if kl_model else None,
           "kl_floor": floor["kl_to_group_mean"], "kl_pairwise_floor": floor["kl_pairwise"],
           "kl_perfect_model_ratio": floor.get("kl_perfect_model_ratio"),
           "file_noise_floor": {k: floor[k] for k in ("pressure_mse_normalised",
                                                      "kl_to_group_mean", "kl_pairwise",
                                                      "kl_perfect_model_ratio")}}
    out["pressure_mse_ratio"] = (out["pressure_mse_normalised_model"]
                                 / out["pressure_mse_normalised_floor"]
                                 if out["pressure_mse_normalised_floor"] > 0 else None)
    out["kl_ratio"] = (out["kl_model"] / out["kl_floor"]
                       if out["kl_model"] is not None and out["kl_floor"] else None)
    return out


def seed_mean_comparison(model: SurrogateModel, ds: Dataset, role: str = "holdout",
                         kl_simulations: int = 200, pred=None) -> dict | None:
    """Model error against the seed means of the ``role`` groups (the surrogate's test
    targets: a single chaotic run is not one), next to what the true mean function would
    score against them.

    Targets: :func:`calendaring.data.dataset.seed_means` (mean pressure, pooled events).
    Pressure floor: the mean over groups of the per-point seed variance divided by the
    group's run count (ddof 1, the model's normalisation): the expected MSE of the exact
    mean curve against a mean of that many seeds. Distribution: the model's mean KL(pooled
    || prediction) against ``kl_perfect``, the mean over the same groups of
    :func:`calendaring.data.dataset.perfect_model_kl` (the pooled histogram standing in for
    the true distribution, as many events as pooled). Targets: the paper's test MSE
    (Table 3, 0.0003) and a KL within ``KL_PERFECT_FACTOR`` of the perfect-model figure.
    None without a group of >= 2 runs. ``pred``: the model's prediction for the seed means
    (in :func:`seed_means` order), if already made.
    """
    means = seed_means(ds, role)
    if len(means) == 0:
        return None
    pred = pred or model.predict_unit(means.unit_params)
    floors, perfect, kl_model = [], [], []
    for i, g in enumerate(means.group):
        idx = np.nonzero((ds.group == g) & (ds.role == role))[0]
        x = model.normalise_pressure(ds.pressure[idx])
        floors.append(float(x.var(axis=0, ddof=1).mean() / len(idx)))
        if means.n_events[i] > 0:
            if kl_simulations:
                perfect.append(perfect_model_kl(means.histogram[i], int(means.n_events[i]),
                                                kl_simulations, seed=int(g)))
            kl_model.append(float(kl_divergence(means.histogram[i], pred.distribution[i])))
    out = {"role": role, "groups": len(means), "runs": int(means.seed.sum()),
           "runs_per_group": [int(k) for k in means.seed],
           "metrics": model_metrics(model, means, np.arange(len(means)), pred),
           "pressure_mse_normalised_floor": float(np.mean(floors)),
           "kl_model": float(np.mean(kl_model)) if kl_model else None,
           "kl_perfect": float(np.mean(perfect)) if perfect else None,
           "targets": {"pressure_mse_normalised": PAPER_TABLE3["test"]["mse"],
                       "kl_over_perfect": KL_PERFECT_FACTOR}}
    mse = out["metrics"]["pressure"]["pressure_mse_normalised"]
    out["pressure_mse_normalised"] = mse
    out["pressure_mse_over_floor"] = mse / out["pressure_mse_normalised_floor"] \
        if out["pressure_mse_normalised_floor"] > 0 else None
    out["kl_over_perfect"] = out["kl_model"] / out["kl_perfect"] \
        if out["kl_model"] is not None and out["kl_perfect"] else None
    out["meets"] = {"pressure_mse_normalised": bool(mse <= PAPER_TABLE3["test"]["mse"]),
                    "kl_over_perfect": None if out["kl_over_perfect"] is None
                    else bool(out["kl_over_perfect"] <= KL_PERFECT_FACTOR)}
    return out


def baseline_metrics(model: SurrogateModel, ds: Dataset, train_rows, test_rows,
                     n_components: int = 8, seed: int = 0, test_ds: Dataset | None = None
                     ) -> dict:
    """PCA + GP baseline fitted on ``train_rows`` of ``ds`` (in the model's normalisation)
    and scored with :func:`pressure_errors` on ``test_rows`` of ``test_ds`` (default
    ``ds``; e.g. the held-out seed means of :func:`calendaring.data.dataset.seed_means`)."""
    t0 = time.perf_counter()
    test_ds = ds if test_ds is None else test_ds
    b = PCAGPBaseline(n_components, seed).fit(
        ds.unit_params[train_rows], model.normalise_pressure(ds.pressure[train_rows]))
    mean, sd = b.predict(test_ds.unit_params[test_rows])
    truth = test_ds.pressure[test_rows]
    out = pressure_errors(truth, model.pressure_from_normalised(mean), model)
    err = np.abs(mean - model.normalise_pressure(truth))
    out["coverage_2sigma"] = float(np.mean(err <= 2 * sd))
    out["n_components"] = len(b.gps)
    out["fit_seconds"] = time.perf_counter() - t0
    return out


# ---------------------------------------------------------------------- cross-validation
def _summary(per_fold: list[dict], keys: dict[str, tuple[str, ...]]) -> dict:
    out = {}
    for name, path in keys.items():
        vals = []
        for f in per_fold:
            v = f
            for k in path:
                v = v.get(k) if isinstance(v, dict) else None
            if v is not None:
                vals.append(float(v))
        if vals:
            out[name] = {"mean": float(np.mean(vals)), "std": float(np.std(vals, ddof=1))
                         if len(vals) > 1 else 0.0, "n": len(vals)}
    return out


_CV_KEYS = {
    "mlp_pressure_mse_normalised": ("mlp", "pressure", "pressure_mse_normalised"),
    "mlp_pressure_rmse_Pa": ("mlp", "pressure", "pressure_rmse_Pa"),
    "mlp_rel_error_100%": ("mlp", "pressure", "at_stroke", "100%", "rel_error_mean"),
    "mlp_rel_error_50%": ("mlp", "pressure", "at_stroke", "50%", "rel_error_mean"),
    "mlp_kl_mean": ("mlp", "distribution", "kl_mean"),
    "mlp_centroid_load_rel_error": ("mlp", "distribution", "centroid_load_rel_error_mean"),
    "mlp_centroid_diameter_abs_error_m": ("mlp", "distribution",
                                          "centroid_diameter_abs_error_m_mean"),
    "baseline_pressure_mse_normalised": ("baseline", "pressure_mse_normalised"),
    "baseline_pressure_rmse_Pa": ("baseline", "pressure_rmse_Pa"),
    "baseline_rel_error_100%": ("baseline", "at_stroke", "100%", "rel_error_mean"),
}


def cross_validate(ds: Dataset, folds: int = 5, repeats: int = 2, cfg: TrainConfig | None = None,
                   model_config: ModelConfig | None = None, baseline: bool = True,
                   progress: bool = True) -> dict:
    """Repeated K-fold cross-validation of a single MLP (and the PCA + GP baseline).

    The trainable rows (``cfg.train_roles``) are split by scikit-learn ``RepeatedKFold``
    (seeded by ``cfg.seed``). In each fold the training part loses a random 1/9 to
    validation (early stopping), the normalisation is fitted on the rest, and both models
    are scored on the test fold in the fold model's normalisation.
    """
    from sklearn.model_selection import RepeatedKFold

    cfg = replace(cfg or TrainConfig(), snapshot_epochs=())
    rows = trainable_rows(ds, cfg.train_roles)
    if not 2 <= int(folds) <= len(rows):
        raise ConfigError("--folds", folds, f"an integer in [2, {len(rows)}]")
    if int(repeats) < 1:
        raise ConfigError("--repeats", repeats, "an integer >= 1")
    rkf = RepeatedKFold(n_splits=int(folds), n_repeats=int(repeats), random_state=cfg.seed)
    per_fold = []
    bar = tqdm(list(rkf.split(rows)), desc="cross-validation", file=sys.stderr,
               disable=not progress, unit="fold")
    for i, (tr, te) in enumerate(bar):
        tr_rows, te_rows = rows[tr], rows[te]
        perm = np.random.default_rng(cfg.seed + i).permutation(len(tr_rows))
        n_val = max(1, round(len(tr_rows) / 9))
        val, fit = np.sort(tr_rows[perm[:n_val]]), np.sort(tr_rows[perm[n_val:]])
        net, norm, _, _ = fit_rows(ds, fit, val, cfg, model_config, progress=False)
        sm = SurrogateModel([net], norm, ds.space, ds.depth, ds.load_edges, ds.diameter_edges,
                            ds.load_scale, {"train_config": cfg.to_dict()})
        fold = {"fold": i, "n_train": len(fit), "n_val": len(val), "n_test": len(te_rows),
                "mlp": model_metrics(sm, ds, te_rows)}
        if baseline:
            fold["baseline"] = baseline_metrics(sm, ds, tr_rows, te_rows, seed=cfg.seed)
        per_fold.append(fold)
        bar.set_postfix(mse=f"{fold['mlp']['pressure']['pressure_mse_normalised']:.3g}")
    return {"folds": int(folds), "repeats": int(repeats), "epochs": cfg.epochs,
            "summary": _summary(per_fold, _CV_KEYS), "per_fold": per_fold}


# ---------------------------------------------------------------------- Table 3 and figures
def loss_table_markdown(table: dict[str, dict], title: str = "Loss per branch") -> str:
    """Table 3 layout: rows train / val / test; MSE, KL and weighted total, with the paper's
    values alongside."""
    lines = [f"### {title}", "",
             "| split | rows | Press. branch (MSE, normalised) | Dist. branch (KL) | "
             "Weighted total | paper MSE / KL / total |", "|---|---|---|---|---|---|"]
    for split in ("train", "val", "test"):
        t = table.get(split)
        if not t:
            continue
        pp = PAPER_TABLE3[split]
        lines.append(f"| {split} | {t.get('n_rows', '')} | {t['mse']:.5f} | {t['kl']:.4f} | "
                     f"{t['total']:.4f} | {pp['mse']} / {pp['kl']} / {pp['total']} |")
    return "\n".join(lines) + "\n"


def pca_convergence_figure(snapshots: dict[int, dict[str, np.ndarray]], path: str | Path
                           ) -> Path | None:
    """Fig. 5: for each snapshot epoch, PC1 of true vs predicted pressure curves (left) and
    true (green) and predicted (orange) distributions on the true data's first two principal
    components (right). Components are fitted on the true samples of the last epoch."""
    from matplotlib.figure import Figure
    from sklearn.decomposition import PCA

    epochs = sorted(snapshots)
    if not epochs or len(snapshots[epochs[-1]]["pressure_true"]) < 3:
        return None
    last = snapshots[epochs[-1]]
    pca_p = PCA(1).fit(last["pressure_true"])
    d_true_flat = last["dist_true"].reshape(len(last["dist_true"]), -1)
    pca_d = PCA(2).fit(d_true_flat) if len(d_true_flat) >= 3 else None
    fig = Figure(figsize=(9, 3.2 * len(epochs)), layout="constrained")
    axes = fig.subplots(len(epochs), 2, squeeze=False)
    for row, e in enumerate(epochs):
        s = snapshots[e]
        a = axes[row, 0]
        t1 = pca_p.transform(s["pressure_true"])[:, 0]
        p1 = pca_p.transform(s["pressure_pred"])[:, 0]
        lim = [min(t1.min(), p1.min()), max(t1.max(), p1.max())]
        a.scatter(t1, p1, s=10, color="tab:blue", alpha=0.7)
        a.plot(lim, lim, "k--", lw=1)
        a.set_xlabel("PC1 of true pressure")
        a.set_ylabel("PC1 of predicted pressure")
        a.set_title(f"epoch {e}: pressure branch")
        a = axes[row, 1]
        if pca_d is not None and len(s["dist_true"]):
            tt = pca_d.transform(s["dist_true"].reshape(len(s["dist_true"]), -1))
            pp = pca_d.transform(s["dist_pred"].reshape(len(s["dist_pred"]), -1))
            a.scatter(tt[:, 0], tt[:, 1], s=10, color="tab:green", alpha=0.5, label="true")
            a.scatter(pp[:, 0], pp[:, 1], s=10, color="tab:orange", alpha=0.5, label="predicted")
            a.legend(loc="best", fontsize=8)
        a.set_xlabel("PC1")
        a.set_ylabel("PC2")
        a.set_title(f"epoch {e}: distribution branch")
    return _save_figure(fig, path)


def loss_history_figure(histories: list[dict], path: str | Path) -> Path | None:
    """Training and validation losses (total, MSE, KL) per epoch for each member."""
    from matplotlib.figure import Figure

    if not histories:
        return None
    fig = Figure(figsize=(12, 3.5), layout="constrained")
    axes = fig.subplots(1, 3)
    for k, h in enumerate(histories):
        for a, term in zip(axes, ("total", "mse", "kl"), strict=True):
            ep = np.arange(1, len(h[f"train_{term}"]) + 1)
            a.plot(ep, h[f"train_{term}"], color="tab:blue", alpha=0.8,
                   label="train" if k == 0 else None)
            a.plot(ep, h[f"val_{term}"], color="tab:red", alpha=0.8,
                   label="validation" if k == 0 else None)
            a.set_yscale("log")
            a.set_xlabel("epoch")
            a.set_title({"total": "weighted total", "mse": "pressure MSE (normalised)",
                         "kl": "distribution KL"}[term])
    axes[0].legend()
    return _save_figure(fig, path)


def pressure_examples_figure(model: SurrogateModel, ds: Dataset, rows, path: str | Path,
                             n: int = 6) -> Path | None:
    """True and predicted pressure curves (MPa against depth in micrometres) for up to ``n``
    rows, with the ensemble's 2-sigma band."""
    from matplotlib.figure import Figure

    rows = np.asarray(rows, dtype=int)[:n]
    if len(rows) == 0:
        return None
    pred = model.predict_unit(ds.unit_params[rows])
    fig = Figure(figsize=(12, 6), layout="constrained")
    axes = fig.subplots(2, 3).ravel()
    z = model.depth * 1e6
    for a, i, k in zip(axes, rows, range(len(rows)), strict=False):
        a.plot(z, ds.pressure[i] / 1e6, "k-", lw=1.5, label="dataset")
        a.plot(z, pred.pressure[k] / 1e6, "tab:orange", lw=1.2, label="surrogate")
        if pred.pressure_std is not None:
            a.fill_between(z, (pred.pressure[k] - 2 * pred.pressure_std[k]) / 1e6,
                           (pred.pressure[k] + 2 * pred.pressure_std[k]) / 1e6,
                           color="tab:orange", alpha=0.25, label="ensemble 2 sigma")
        a.set_title(str(ds.run_id[i]), fontsize=9)
        a.set_xlabel("depth [um]")
        a.set_ylabel("pressure [MPa]")
    axes[0].legend(fontsize=8)
    return _save_figure(fig, path)


# ---------------------------------------------------------------------- driver
def check_compatible(model: SurrogateModel, ds: Dataset) -> None:
    """Raise :class:`ConfigError` if the dataset's depths, bins or parameters differ."""
    if ds.space.names != model.space.names:
        raise ConfigError("dataset parameters", ds.space.names, f"{model.space.names}")
    if ds.depth.shape != model.depth.shape or not np.allclose(ds.depth, model.depth, rtol=1e-9):
        raise ConfigError("dataset pressure/depth", f"{len(ds.depth)} depths to "
                          f"{ds.depth[-1]:.4g} m", f"the model's {len(model.depth)} depths to "
                          f"{model.depth[-1]:.4g} m")
    for name in ("load_edges", "diameter_edges"):
        a, b = getattr(ds, name), getattr(model, name)
        if a.shape != b.shape or not np.allclose(a, b, rtol=1e-9):
            raise ConfigError(f"dataset distribution/{name}", f"{len(a)} edges",
                              "the model's bin edges")


def split_rows(model: SurrogateModel, ds: Dataset) -> dict[str, np.ndarray] | None:
    """The training run's split as row indices of ``ds`` (None if ``ds`` is not the
    training dataset, judged by its fingerprint)."""
    info = model.info
    if info.get("dataset", {}).get("fingerprint") != ds.fingerprint or "split" not in info:
        return None
    where = {str(r): i for i, r in enumerate(ds.run_id)}
    return {k: np.array([where[r] for r in ids if r in where], dtype=int)
            for k, ids in info["split"].items()}


def evaluate(model: SurrogateModel, ds: Dataset, out_dir: str | Path | None = None,
             folds: int = 0, repeats: int = 1, epochs: int | None = None,
             baseline: bool = True, progress: bool = True) -> dict:
    """Evaluate ``model`` on ``ds``; write metrics, Table 3 and figures to ``out_dir``.

    Args:
        model: a loaded surrogate (single or ensemble).
        ds: a dataset with the model's depths and bin edges.
        out_dir: folder for ``metrics.json``, ``loss_table.{json,md}``, ``cv.json`` and the
            PNG figures (nothing is written when None).
        folds, repeats: repeated K-fold cross-validation (off when ``folds`` is 0); each fold
            trains a single model with the checkpoint's training settings.
        epochs: epochs per cross-validation fit (default: the checkpoint's).
        baseline: also fit the PCA + GP baseline.
        progress: tqdm bars on stderr.

    Returns:
        The metrics dictionary (also written as ``metrics.json``).
    """
    check_compatible(model, ds)
    out: dict = {"model": {"path": model.info.get("path"), "members": model.n_members,
                           "is_ensemble": model.is_ensemble,
                           "normalisation": model.normalisation.to_dict(),
                           "trained_on": model.info.get("dataset", {})},
                 "dataset": {"path": str(ds.path or ""), "fingerprint": ds.fingerprint,
                             "rows": len(ds),
                             "roles": {r: int(np.sum(ds.role == r)) for r in sorted(set(ds.role))}},
                 "units": {"pressure_mse_normalised": "normalised cube-root units (1)",
                           "_Pa": "Pa", "_Pa2": "Pa^2", "_m": "m", "kl": "nat",
                           "rel_error": "1 (fraction)"}}
    split = split_rows(model, ds)
    out["same_dataset_as_training"] = split is not None
    sets: dict[str, np.ndarray] = {}
    if split is not None:
        sets["test"] = split["test"]
        table = {k: loss_terms(model, ds.subset(v)) for k, v in split.items() if len(v)}
        out["loss_table"] = table
        out["loss_table_members"] = [m.get("loss_table") for m in model.info.get("members", [])]
    else:
        sets["all_train_role"] = np.nonzero(ds.role == "train")[0]
    hold = np.nonzero(ds.role == "holdout")[0]
    if len(hold):
        sets["holdout"] = hold
    rep = np.nonzero(ds.role == "replicate")[0]
    if len(rep):
        sets["replicate"] = rep
    out["metrics"] = {name: model_metrics(model, ds, rows) for name, rows in sets.items()}
    out["replicates"] = rep_cmp = replicate_comparison(model, ds)
    out["holdout_means"] = seed_mean_comparison(model, ds)
    main_set = next(iter(sets))
    if rep_cmp is not None and out["metrics"][main_set].get("pressure"):
        m = out["metrics"][main_set]
        kl = m["distribution"].get("kl_mean")
        fp, fk = rep_cmp["pressure_mse_normalised_floor"], rep_cmp["kl_floor"]
        out["noise_floor_comparison"] = {
            "rows": main_set, "pressure_mse_normalised": m["pressure"]["pressure_mse_normalised"],
            "pressure_mse_normalised_floor": fp, "kl_mean": kl, "kl_floor": fk,
            "pressure_mse_over_floor": m["pressure"]["pressure_mse_normalised"] / fp
            if fp else None,
            "kl_over_floor": kl / fk if (kl is not None and fk) else None,
            "kl_perfect_model_ratio": rep_cmp.get("kl_perfect_model_ratio")}
    if baseline and split is not None and len(split["test"]):
        train_rows = np.concatenate([split["train"], split["val"]])
        out["baseline_test"] = baseline_metrics(model, ds, train_rows, split["test"])
        if out["holdout_means"] is not None:
            means = seed_means(ds)
            out["baseline_holdout_means"] = baseline_metrics(
                model, ds, train_rows, np.arange(len(means)), test_ds=means)
    if folds:
        cfg = TrainConfig.from_dict(model.info.get("train_config", {}))
        if epochs is not None:
            cfg = replace(cfg, epochs=int(epochs))
        out["cross_validation"] = cross_validate(ds, folds, repeats, cfg, model.config,
                                                 baseline, progress)
    if out_dir is not None:
        out["files"] = write_outputs(out, model, ds, sets, Path(out_dir))
    return out


def write_outputs(out: dict, model: SurrogateModel, ds: Dataset, sets: dict, out_dir: Path
                  ) -> list[str]:
    """Write the metrics JSON, Table 3 and the figures; returns the file names."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    if "loss_table" in out:
        write_json(out_dir / "loss_table.json", {"loss_table": out["loss_table"],
                                                 "paper_table3": PAPER_TABLE3,
                                                 "weights": {"mse": MSE_WEIGHT, "kl": KL_WEIGHT}})
        title = "Loss per branch (ensemble mean)" if model.is_ensemble else "Loss per branch"
        write_text(out_dir / "loss_table.md", loss_table_markdown(out["loss_table"], title))
        files += ["loss_table.json", "loss_table.md"]
    if "cross_validation" in out:
        write_json(out_dir / "cv.json", out["cross_validation"])
        files.append("cv.json")
    if pca_convergence_figure(model.snapshots, out_dir / "pca_convergence.png"):
        files.append("pca_convergence.png")
    hist = [m["history"] for m in model.info.get("members", []) if "history" in m]
    if loss_history_figure(hist, out_dir / "loss_history.png"):
        files.append("loss_history.png")
    rows = next(iter(sets.values()), np.zeros(0, int))
    if pressure_examples_figure(model, ds, rows, out_dir / "pressure_examples.png"):
        files.append("pressure_examples.png")
    files.append("metrics.json")
    body = {k: v for k, v in out.items() if k != "cross_validation"}
    if "cross_validation" in out:
        body["cross_validation_summary"] = out["cross_validation"]["summary"]
    body["files"] = files
    write_json(out_dir / "metrics.json", body)
    return files


def summary_lines(out: dict) -> list[str]:
    """A short printed summary (MPa and percent for reading; the files stay SI)."""
    lines = []
    for name, m in out.get("metrics", {}).items():
        if not m.get("pressure"):
            continue
        p, d = m["pressure"], m["distribution"]
        at = p["at_stroke"]
        lines.append(f"{name} ({p['n_rows']} runs): pressure MSE {p['pressure_mse_normalised']:.3g}"
                     f" (normalised), RMSE {p['pressure_rmse_Pa'] / 1e6:.3g} MPa, relative error "
                     + ", ".join(f"{k} {v['rel_error_mean'] * 100:.2f}%"
                                 for k, v in at.items() if v["rel_error_mean"] is not None)
                     + (f"; KL {d['kl_mean']:.3g}, load-centroid error "
                        f"{d['centroid_load_rel_error_mean'] * 100:.2f}%, diameter-centroid error "
                        f"{d['centroid_diameter_abs_error_m_mean'] * 1e6:.3g} um"
                        if d.get("n_rows") else ""))
    r = out.get("replicates")
    if r:
        def g(v):
            return "n/a" if v is None else f"{v:.3g}"
        lines.append(f"replicates ({r['groups']} groups): pressure MSE "
                     f"{g(r['pressure_mse_normalised_model'])} vs floor "
                     f"{g(r['pressure_mse_normalised_floor'])}; KL {g(r['kl_model'])} vs floor "
                     f"{g(r['kl_floor'])}"
                     + (f" (a perfect model would score {r['kl_perfect_model_ratio']:.3g} x "
                        "the KL floor)" if r.get("kl_perfect_model_ratio") else ""))
    h = out.get("holdout_means")
    if h:
        p = h["metrics"]["pressure"]
        at = ", ".join(f"{k} {v['abs_error_Pa'] / 1e6:.3g} MPa"
                       for k, v in p["at_stroke"].items())
        kl = "" if h["kl_model"] is None else (
            f"; KL {h['kl_model']:.3g}" + (f" vs {h['kl_perfect']:.3g} for a perfect model "
                                           f"({h['kl_over_perfect']:.2f} x, target "
                                           f"{KL_PERFECT_FACTOR} x)" if h["kl_perfect"] else ""))
        lines.append(f"held-out seed means ({h['groups']} groups of "
                     f"{min(h['runs_per_group'])}-{max(h['runs_per_group'])} seeds): pressure "
                     f"MSE {h['pressure_mse_normalised']:.3g} (normalised; target "
                     f"{h['targets']['pressure_mse_normalised']:g}, the exact mean curve would "
                     f"score {h['pressure_mse_normalised_floor']:.3g}), error {at}{kl}")
    for key, what in (("baseline_test", "test"), ("baseline_holdout_means",
                                                   "held-out seed means")):
        b = out.get(key)
        if b:
            lines.append(f"PCA+GP baseline ({what}): pressure MSE "
                         f"{b['pressure_mse_normalised']:.3g} (normalised), RMSE "
                         f"{b['pressure_rmse_Pa'] / 1e6:.3g} MPa")
    cv = out.get("cross_validation")
    if cv:
        for k, v in cv["summary"].items():
            lines.append(f"CV {cv['folds']}x{cv['repeats']}: {k} = {v['mean']:.4g} "
                         f"+- {v['std']:.2g}")
    return lines


__all__ = ["KL_PERFECT_FACTOR", "PAPER_TABLE3", "STROKE_FRACTIONS", "baseline_metrics",
           "check_compatible", "cross_validate", "distribution_errors", "evaluate",
           "loss_history_figure", "loss_table_markdown", "loss_terms", "model_metrics",
           "pca_convergence_figure", "pressure_errors", "pressure_examples_figure",
           "replicate_comparison", "seed_mean_comparison", "split_rows", "summary_lines",
           "write_json", "write_text"]

"""How far training settings move the surrogate's test error on one dataset.

Trains one model per (setting, split) over a small grid of loss weights, dropout, weight
decay, learning rate and batch size, on the 8:1:1 splits of seeds ``--splits`` (each seed
draws another split, so the spread between seeds is the split-to-split scatter of a 28-row
test set), and fits the PCA + Gaussian-process baseline on the same training rows. Reports
the test pressure MSE (normalised cube-root units) and the distribution KL per split and
their means, next to the dataset's replicate noise floors.

Then a learning curve of the PCA + GP baseline: fitted on 25/50/75/100 % of each split's
training and validation rows (three random subsets below 100 %), scored on the split's
test rows, and ``a + b n^-c`` fitted to the mean test MSE against n (scipy
``curve_fit``): ``a`` estimates the error no amount of data of this kind removes.

    python benchmarks/bench_surrogate_tuning.py data/reference.h5 [--splits 0 1 2]

Writes JSON (atomically) to ``benchmarks/results/bench_surrogate_tuning.json``. One thread.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from calendaring import read_dataset, write_json
from surrogate.api import SurrogateModel
from surrogate.baseline import PCAGPBaseline
from surrogate.data import Normalisation
from surrogate.evaluate import model_metrics, replicate_comparison
from surrogate.model import ModelConfig
from surrogate.train import TrainConfig, make_split, train

# (name, TrainConfig overrides, dropout); the first is the paper's configuration
GRID = [
    ("paper (0.7 MSE + 0.3 KL, dropout 0.3)", {}, 0.3),
    ("MSE weight 30", {"mse_weight": 30.0}, 0.3),
    ("MSE weight 300", {"mse_weight": 300.0}, 0.3),
    ("MSE weight 30, dropout 0.1", {"mse_weight": 30.0}, 0.1),
    ("MSE weight 30, dropout 0.2", {"mse_weight": 30.0}, 0.2),
    ("MSE weight 30, dropout 0", {"mse_weight": 30.0}, 0.0),
    ("MSE weight 30, dropout 0.1, weight decay 1e-4",
     {"mse_weight": 30.0, "weight_decay": 1e-4}, 0.1),
    ("MSE weight 30, dropout 0.1, lr 5e-4, 150 epochs (patience 30)",
     {"mse_weight": 30.0, "lr": 5e-4, "epochs": 150, "patience": 30}, 0.1),
    ("MSE weight 30, dropout 0.1, batch 32", {"mse_weight": 30.0, "batch_size": 32}, 0.1),
    ("dropout 0.1, 200 epochs (patience 40)", {"epochs": 200, "patience": 40}, 0.1),
]


def learning_curve(ds, splits, fractions=(0.25, 0.5, 0.75, 1.0), subsets: int = 3) -> dict:
    """Test MSE of the PCA + GP baseline against the number of training rows."""
    from scipy.optimize import curve_fit

    points = []
    for frac in fractions:
        mse, n_rows = [], 0
        for seed in splits:
            split = make_split(ds, TrainConfig(seed=seed))
            pool = np.concatenate([split["train"], split["val"]])
            for k in range(1 if frac >= 1.0 else subsets):
                n_rows = round(frac * len(pool))
                tr = np.random.default_rng(k).permutation(pool)[:n_rows]
                y = Normalisation.fit(ds.pressure[tr]).normalise(ds.pressure)
                mean, _ = PCAGPBaseline().fit(ds.unit_params[tr], y[tr]).predict(
                    ds.unit_params[split["test"]])
                mse.append(float(np.mean((mean - y[split["test"]]) ** 2)))
        points.append({"fraction": frac, "n_rows": n_rows,
                       "pressure_mse_mean": float(np.mean(mse)),
                       "pressure_mse_se": float(np.std(mse, ddof=1) / np.sqrt(len(mse))),
                       "fits": len(mse)})
    n = np.array([p["n_rows"] for p in points], float)
    y = np.array([p["pressure_mse_mean"] for p in points])
    se = np.array([p["pressure_mse_se"] for p in points])
    par, cov = curve_fit(lambda x, a, b, c: a + b * x ** (-c), n, y, p0=(y[-1] / 2, 0.1, 1.0),
                         sigma=np.maximum(se, 1e-12), maxfev=20000)
    err = np.sqrt(np.diag(cov))
    return {"points": points,
            "fit": {"model": "a + b n^-c", "a": float(par[0]), "b": float(par[1]),
                    "c": float(par[2]), "a_se": float(err[0]), "c_se": float(err[2]),
                    "predicted_at": {str(m): float(par[0] + par[1] * m ** (-par[2]))
                                     for m in (500, 1000, 2000)}}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", help="dataset file (e.g. data/reference.h5)")
    ap.add_argument("--splits", type=int, nargs="+", default=[0, 1, 2],
                    help="split seeds (default 0 1 2)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" /
                                         "bench_surrogate_tuning.json"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    ds = read_dataset(args.dataset)
    t_all = time.perf_counter()
    rows_out = []
    floors = None
    for name, over, dropout in GRID:
        per = []
        for seed in args.splits:
            t0 = time.perf_counter()
            res = train(ds, TrainConfig(seed=seed, **over), ModelConfig(dropout=dropout),
                        progress=False)
            model = SurrogateModel.from_training(res, ds)
            test = model_metrics(model, ds, res.rows["test"])
            if floors is None:
                rep = replicate_comparison(model, ds)
                floors = None if rep is None else {
                    "pressure_mse_normalised": rep["pressure_mse_normalised_floor"],
                    "kl": rep["kl_floor"]}
            per.append({"split_seed": seed,
                        "pressure_mse": test["pressure"]["pressure_mse_normalised"],
                        "kl": test["distribution"].get("kl_mean"),
                        "best_epoch": res.history.best_epoch,
                        "seconds": time.perf_counter() - t0})
        mse = np.array([p["pressure_mse"] for p in per])
        kl = np.array([p["kl"] for p in per], dtype=float)
        rows_out.append({"setting": name, "train_config": over, "dropout": dropout,
                         "pressure_mse_mean": float(mse.mean()), "kl_mean": float(kl.mean()),
                         "per_split": per})
        print(f"{name}: test MSE {mse.mean():.5f} ({', '.join(f'{x:.5f}' for x in mse)}), "
              f"KL {kl.mean():.3f}", file=sys.stderr, flush=True)

    gp = []
    for seed in args.splits:
        split = make_split(ds, TrainConfig(seed=seed))  # the MLP's split of this seed
        tr, te = split["train"], split["test"]
        y = Normalisation.fit(ds.pressure[tr]).normalise(ds.pressure)
        b = PCAGPBaseline().fit(ds.unit_params[tr], y[tr])
        mean, _ = b.predict(ds.unit_params[te])
        gp.append({"split_seed": seed, "pressure_mse": float(np.mean((mean - y[te]) ** 2))})
    gp_mean = float(np.mean([g["pressure_mse"] for g in gp]))
    print(f"PCA + GP baseline: test MSE {gp_mean:.5f}", file=sys.stderr)

    curve = learning_curve(ds, args.splits)
    print("learning curve (PCA + GP): " + ", ".join(
        f"n={c['n_rows']}: {c['pressure_mse_mean']:.5f}" for c in curve["points"]) +
          f"; asymptote {curve['fit']['a']:.5f} +- {curve['fit']['a_se']:.5f}",
          file=sys.stderr)

    out = {"benchmark": "surrogate_tuning", "dataset": {"path": args.dataset,
                                                        "fingerprint": ds.fingerprint},
           "splits": args.splits, "threads": 1, "loadavg_at_end": os.getloadavg(),
           "seconds": time.perf_counter() - t_all, "replicate_floors": floors,
           "settings": rows_out,
           "pca_gp_baseline": {"pressure_mse_mean": gp_mean, "per_split": gp},
           "pca_gp_learning_curve": curve,
           "target": {"pressure_mse_normalised_max": 3e-4, "kl_over_floor_max": 1.2}}
    path = Path(args.out)
    write_json(path, out, indent=2)  # atomic; NaN -> null
    print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

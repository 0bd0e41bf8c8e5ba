"""Surrogate benchmark: training time, prediction throughput, test-split accuracy.

On a dataset file (default: the analytic stand-in ``synthetic_dataset(300,
replicate_groups=3, replicates=5, noise=0.02)``, clearly not DEM data) this measures

- the wall time to train one paper model for ``--epochs`` (80) epochs, early stopping off;
- prediction throughput in parameter sets per second on CPU, through the public API
  (``SurrogateModel.predict_unit``, NumPy in and out) and the bare torch forward pass, in
  batches of ``--batch`` rows, for each thread count in ``--threads``; the API both in
  float32 and under bfloat16 autocast (``precision="bfloat16"``), with how far the
  bfloat16 predictions lie from the float32 ones on the test rows;
- the test-split pressure MSE in normalised cube-root units and the distribution KL, next
  to the replicate noise floor and the paper's figures (0.0003, 0.33).

Writes JSON (atomically) to ``benchmarks/results/bench_surrogate.json``. Targets (issue 6)
are checked here, never in tests.

    python benchmarks/bench_surrogate.py [DATASET.h5] [--epochs 80] [--threads 1 2]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from calendaring import read_dataset, synthetic_dataset, write_json
from surrogate.api import PRECISIONS, SurrogateModel
from surrogate.evaluate import model_metrics, replicate_comparison
from surrogate.losses import kl_per_row
from surrogate.train import TrainConfig, train

TARGETS = {"pressure_mse_normalised_max": 3e-4, "kl_over_floor_max": 1.2,
           "train_seconds_80_epochs_max": 60.0, "predictions_per_second_min": 1e5}


def throughput(model: SurrogateModel, batch: int, repeats: int = 15) -> dict:
    """Best-of-``repeats`` rows per second of the API (float32 and bfloat16) and of the bare
    float32 forward pass."""
    u = np.random.default_rng(0).random((batch, len(model.space)))
    ut = torch.as_tensor(u, dtype=torch.float32)
    net = model.members[0].eval()
    for prec in PRECISIONS:  # warm-up
        model.predict_unit(u[:64], precision=prec)
    api = {p: [] for p in PRECISIONS}
    raw = []
    for _ in range(repeats):
        for prec in PRECISIONS:
            t = time.perf_counter()
            model.predict_unit(u, batch_size=batch, precision=prec)
            api[prec].append(batch / (time.perf_counter() - t))
        with torch.inference_mode():
            t = time.perf_counter()
            net(ut)
            raw.append(batch / (time.perf_counter() - t))
    return {"batch": batch, "api_per_s": max(api["float32"]),
            "api_bfloat16_per_s": max(api["bfloat16"]), "forward_per_s": max(raw)}


def precision_cost(model: SurrogateModel, u: np.ndarray) -> dict:
    """How far bfloat16 predictions lie from float32 ones on the rows ``u``."""
    a = model.predict_unit(u)
    b = model.predict_unit(u, precision="bfloat16")
    kl = kl_per_row(torch.as_tensor(a.distribution), torch.as_tensor(b.distribution)).numpy()
    rel = np.abs(b.pressure - a.pressure) / np.maximum(np.abs(a.pressure), 1.0)
    return {"rows": len(u),
            "pressure_mse_normalised": float(np.mean((a.pressure_normalised
                                                      - b.pressure_normalised) ** 2)),
            "pressure_rel_diff_max": float(rel[:, 20:].max()),
            "kl_mean": float(np.mean(kl))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", nargs="?", help="dataset file (default: synthetic, 300 runs)")
    ap.add_argument("--epochs", type=int, default=80)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train-threads", type=int, default=1)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2],
                    help="thread counts for the throughput measurement")
    ap.add_argument("--batch", type=int, nargs="+", default=[1024, 8192])
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" /
                                         "bench_surrogate.json"))
    args = ap.parse_args(argv)

    if args.dataset:
        ds = read_dataset(args.dataset)
        source = {"kind": "file", "path": args.dataset, "fingerprint": ds.fingerprint}
    else:
        ds = synthetic_dataset(300, replicate_groups=3, replicates=5, noise=0.02)
        source = {"kind": "synthetic (analytic stand-in, not DEM data)",
                  "call": "synthetic_dataset(300, replicate_groups=3, replicates=5, noise=0.02)"}
    torch.set_num_threads(args.train_threads)
    load0 = os.getloadavg()
    cfg = TrainConfig(epochs=args.epochs, patience=0, seed=args.seed)
    t0 = time.perf_counter()
    res = train(ds, cfg, progress=True)
    train_s = time.perf_counter() - t0
    model = SurrogateModel.from_training(res, ds)
    test = model_metrics(model, ds, res.rows["test"])
    rep = replicate_comparison(model, ds)

    tp = []
    for n in args.threads:
        torch.set_num_threads(n)
        for b in args.batch:
            tp.append({"threads": n, **throughput(model, b)})
    best = max(t["api_per_s"] for t in tp)
    best_bf16 = max(t["api_bfloat16_per_s"] for t in tp)
    cost = precision_cost(model, ds.unit_params[res.rows["test"]])
    kl, floor = test["distribution"].get("kl_mean"), rep["kl_floor"] if rep else None
    out = {
        "benchmark": "surrogate", "dataset": source, "rows": len(ds),
        "split_rows": {k: len(v) for k, v in res.rows.items()},
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                    "torch": str(torch.__version__), "loadavg_at_start": load0,
                    "loadavg_at_end": os.getloadavg()},
        "train": {"epochs": args.epochs, "threads": args.train_threads, "seconds": train_s,
                  "fit_seconds": res.seconds, "best_epoch": res.history.best_epoch},
        "throughput": tp,
        "bfloat16_vs_float32_on_test_rows": cost,
        "test": {"pressure_mse_normalised": test["pressure"]["pressure_mse_normalised"],
                 "pressure_rmse_Pa": test["pressure"]["pressure_rmse_Pa"],
                 "rel_error_at_stroke": {k: v["rel_error_mean"] for k, v in
                                         test["pressure"]["at_stroke"].items()},
                 "kl_mean": kl, "loss_table": res.loss_table},
        "replicates": rep,
        "paper": {"test_pressure_mse_normalised": 0.0003, "test_kl": 0.33},
        "targets": TARGETS,
        "target_met": {
            "pressure_mse": test["pressure"]["pressure_mse_normalised"]
            <= TARGETS["pressure_mse_normalised_max"],
            "kl_vs_floor": (kl / floor <= TARGETS["kl_over_floor_max"]) if floor else None,
            "train_time": train_s <= TARGETS["train_seconds_80_epochs_max"]
            if args.epochs == 80 else None,
            "throughput": best >= TARGETS["predictions_per_second_min"],
            "throughput_bfloat16": best_bf16 >= TARGETS["predictions_per_second_min"]},
    }
    path = Path(args.out)
    write_json(path, out, indent=2)  # atomic; NaN -> null
    print(f"train {args.epochs} epochs: {train_s:.1f} s ({args.train_threads} thread); "
          f"test MSE {out['test']['pressure_mse_normalised']:.3g} (normalised), KL "
          f"{kl:.3g} (floor {floor}; a perfect model would score "
          f"{rep.get('kl_perfect_model_ratio') if rep else None} x the floor); best "
          f"throughput {best:.3g} sets/s float32, "
          f"{best_bf16:.3g} bfloat16 (MSE shift {cost['pressure_mse_normalised']:.2g}, KL "
          f"{cost['kl_mean']:.2g}); wrote {path}",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

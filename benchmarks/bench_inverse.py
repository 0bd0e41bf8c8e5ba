"""Inverse calibration speed: default calibration, 64 restarts, posterior.

Trains a surrogate with the paper's architecture on the synthetic stand-in dataset
(:func:`calendaring.data.dataset.synthetic_dataset`; the speed of a calibration depends on the
network's size, not on what it learned) unless ``--model MODEL.pt`` is given, then times on a
held-out synthetic curve with its breakage centroid:

1. the paper's default calibration: 500 iterations x 3 restarts, one after the other;
2. 64 Sobol-started restarts, batched, with the optima clustered;
3. the posterior: emcee, 32 walkers x 3000 steps (1000 burn-in), with the predictive band,
   with the centroid and on the pressure curve alone (the distribution head skipped).

Issue targets on 2 CPU cores: (1) under 10 s, (2) under 60 s, (3) under 2 minutes.
Writes ``benchmarks/results/bench_inverse.json`` atomically.

    .venv/bin/python benchmarks/bench_inverse.py --rows 128 --epochs 30
    .venv/bin/python benchmarks/bench_inverse.py --model model.pt --ensemble 0
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TARGETS_S = {"default_500x3": 10.0, "multistart_64": 60.0, "posterior": 120.0}


def train_model(n_rows: int, epochs: int, members: int, seed: int):
    """A surrogate (paper architecture) trained on the synthetic dataset."""
    from calendaring import synthetic_dataset
    from surrogate import ModelConfig, SurrogateModel, TrainConfig, train, train_ensemble

    ds = synthetic_dataset(n=n_rows, seed=seed)
    cfg = TrainConfig(epochs=epochs, patience=0, seed=seed)
    if members > 1:
        return SurrogateModel.from_training(
            train_ensemble(ds, members, cfg, ModelConfig(), progress=False), ds)
    return SurrogateModel.from_training(train(ds, cfg, ModelConfig(), progress=False), ds)


def _time(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", help="surrogate checkpoint (default: train one here)")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch CPU threads (1 is the CLI default: with 2 threads a batch of "
                         "64 restarts ran ~10x slower on a busy 2-core machine)")
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--rows", type=int, default=128, help="synthetic training rows")
    ap.add_argument("--ensemble", type=int, default=3,
                    help="also time the posterior with an ensemble of this many members "
                         "(0: skip)")
    ap.add_argument("--dataset", help="take the target from this dataset (a row with its "
                    "breakage centroid) instead of the synthetic stand-in")
    ap.add_argument("--row", type=int, default=0, help="the --dataset row (default 0)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_inverse.json"))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    import surrogate
    from calendaring import synthetic_dataset
    from inverse.calibrate import calibrate_target
    from inverse.optimise import OptimiserConfig
    from inverse.posterior import PosteriorConfig
    from inverse.report import write_json
    from inverse.validate import row_target

    t0 = time.perf_counter()
    model = surrogate.load(args.model) if args.model else train_model(args.rows, args.epochs,
                                                                      1, 0)
    train_s = time.perf_counter() - t0
    if args.dataset:
        from calendaring import read_dataset

        truth, row, source = read_dataset(args.dataset), args.row, args.dataset
    else:
        truth, row, source = synthetic_dataset(n=1, seed=123), 0, "synthetic"
    target = row_target(model, truth, row)
    print(f"model ready ({train_s:.1f} s); target: {source} row {row} with centroid "
          f"{target.centroids}", file=sys.stderr)
    # warm-up: imports (scipy.stats, torch.optim) and first-call costs, untimed
    calibrate_target(model, target, optimiser=OptimiserConfig(iterations=10, restarts=1),
                     identifiability=False)

    res = {}
    oc, s = _time(lambda: calibrate_target(model, target, optimiser=OptimiserConfig(),
                                           identifiability=False))
    res["default_500x3"] = {"seconds": s, "loss": oc.result["loss"]["total"],
                            "evaluations": oc.result["evaluations"],
                            "fit_relative_rmse": oc.result["fit"]["relative_rmse"],
                            "optimise_seconds": oc.result["timings_s"]["optimise"]}
    print(f"default 500 x 3: {s:.2f} s", file=sys.stderr)
    oc, s = _time(lambda: calibrate_target(model, target, multistart=64, identifiability=False))
    cl = oc.result["clusters"]
    res["multistart_64"] = {"seconds": s, "loss": oc.result["loss"]["total"],
                            "evaluations": oc.result["evaluations"],
                            "within_tolerance": len(cl["within"]),
                            "clusters": len(cl["clusters"])}
    print(f"64 restarts: {s:.2f} s", file=sys.stderr)
    u_opt = np.array(oc.result["parameters_unit"])
    from inverse.identifiability import identifiability_report
    from inverse.loss import CompositeLoss

    loss = CompositeLoss(model, target)
    _, s = _time(lambda: identifiability_report(loss, u_opt, np.ones(8, bool),
                                                model.space.names))  # weights frozen inside
    res["identifiability_slice"] = {"seconds": s}
    from inverse.posterior import sample_posterior

    def post(m, t=target):
        return sample_posterior(m, t, u_opt, np.ones(8, bool), PosteriorConfig(),
                                loss=CompositeLoss(m, t))

    p, s = _time(lambda: post(model))
    res["posterior"] = {"seconds": s, "acceptance": p.diagnostics["acceptance_mean"],
                        "max_autocorr_steps": max(p.diagnostics["autocorr_time"].values()),
                        "log_prob_evaluations": p.diagnostics["log_prob_evaluations"],
                        "walkers": p.diagnostics["walkers"], "steps": p.diagnostics["steps"]}
    print(f"posterior: {s:.2f} s", file=sys.stderr)
    # the same posterior on the curve alone: no centroid term, so the forward passes skip
    # the distribution head (before 7 Dec 2026 they computed it and threw it away)
    curve = replace(target, distribution=None, centroids=None)
    p, s = _time(lambda: post(model, curve))
    res["posterior_pressure_only"] = {
        "seconds": s, "acceptance": p.diagnostics["acceptance_mean"],
        "log_prob_evaluations": p.diagnostics["log_prob_evaluations"]}
    print(f"posterior, pressure curve only: {s:.2f} s", file=sys.stderr)
    if args.ensemble > 1 and not args.model:
        ens = train_model(args.rows, args.epochs, args.ensemble, 0)
        p, s = _time(lambda: post(ens))
        res[f"posterior_ensemble_{args.ensemble}"] = {
            "seconds": s, "acceptance": p.diagnostics["acceptance_mean"],
            "max_autocorr_steps": max(p.diagnostics["autocorr_time"].values())}
        print(f"posterior, ensemble of {args.ensemble}: {s:.2f} s", file=sys.stderr)
    for key, limit in TARGETS_S.items():
        res[key]["target_s"] = limit
        res[key]["meets_target"] = res[key]["seconds"] < limit
    out = {"benchmark": "inverse", "results": res,
           "model": args.model or f"trained here: paper architecture, {args.rows} synthetic "
                                  f"rows, {args.epochs} epochs ({train_s:.1f} s)",
           "machine": {"cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                       "platform": platform.platform(), "torch": torch.__version__,
                       "load_average_1min": os.getloadavg()[0]},
           "target": {"source": args.dataset or "synthetic_dataset(n=1, seed=123)",
                      "row": row, "centroid": target.centroids is not None},
           "command": " ".join([Path(sys.argv[0]).name, *(argv or sys.argv[1:])])}
    write_json(args.out, out)
    print(json.dumps(res, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

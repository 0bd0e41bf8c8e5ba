"""Wall time of a Sobol analysis at N = 2^14 on the surrogate (issue target: under 30 s).

Uses ``MODEL.pt`` when given; otherwise trains a model of the paper's architecture for one
epoch on the synthetic stand-in dataset (the weights do not matter for the timing, the
architecture does). Times, separately:

- ``sobol_n``: one analysis at N (design, N (k + 2) = 163,840 surrogate evaluations with the
  four key outputs, SALib ``analyze.sobol`` with 100 bootstrap resamples for each output);
- ``model_evaluation``: the surrogate evaluations alone;
- ``convergence_study``: the whole ``analysis sobol`` path (:func:`sobol_study`: N = 256 ...
  N on nested designs, the ensemble spread at N/4, JSON and PNGs).

Writes JSON (atomically) to benchmarks/results/bench_sobol.json.

    python benchmarks/bench_sobol.py                     # trained stand-in, one model
    python benchmarks/bench_sobol.py --members 5         # a 5-member deep ensemble
    python benchmarks/bench_sobol.py MODEL.pt --threads 2

Speed targets are checked here, never in tests.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def make_model(members: int, seed: int = 0):
    """A paper-architecture surrogate trained for one epoch on synthetic data."""
    import surrogate
    from calendaring import synthetic_dataset
    from surrogate.api import SurrogateModel
    from surrogate.ensemble import train_ensemble
    from surrogate.train import TrainConfig

    ds = synthetic_dataset(n=64, seed=seed)
    res = train_ensemble(ds, members, TrainConfig(epochs=1, seed=seed, snapshot_epochs=()),
                         progress=False)
    path = Path(tempfile.mkdtemp()) / "bench_model.pt"
    SurrogateModel.from_training(res, ds).save(path)
    return surrogate.load(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", nargs="?", help="surrogate checkpoint (default: train one)")
    ap.add_argument("--n", type=int, default=2**14, help="base sample size (power of two)")
    ap.add_argument("--members", type=int, default=1, help="ensemble size of the trained "
                    "stand-in (ignored with MODEL.pt)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    ap.add_argument("--no-study", action="store_true", help="skip the convergence study")
    ap.add_argument("--out", default=str(ROOT / "benchmarks/results/bench_sobol.json"))
    args = ap.parse_args(argv)

    import torch

    from analysis.plots import atomic_write_json
    from analysis.sensitivity import (
        check_power_of_two,
        evaluate,
        sobol_indices,
        sobol_sample,
        sobol_study,
        surrogate_model,
    )

    if args.threads:
        torch.set_num_threads(args.threads)
    n = check_power_of_two(args.n)
    t = time.perf_counter()
    if args.model:
        import surrogate

        m = surrogate.load(args.model)
    else:
        m = make_model(args.members)
    t_model = time.perf_counter() - t
    names = m.space.names
    model = surrogate_model(m)
    model(sobol_sample(names, 256, 0)[:64])  # warm-up

    t, c = time.perf_counter(), time.process_time()
    u = sobol_sample(names, n, 0)
    evaluate(model, u)
    t_eval, c_eval = time.perf_counter() - t, time.process_time() - c

    t, c = time.perf_counter(), time.process_time()
    res = sobol_indices(model, names, n, seed=0)
    t_sobol, c_sobol = time.perf_counter() - t, time.process_time() - c

    t_study, rows = None, []
    if not args.no_study:
        t = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            study = sobol_study(m, tmp, n=n, n_min=256, seed=0, progress=False)
        t_study = time.perf_counter() - t
        rows = study["convergence"]

    out = {
        "benchmark": "bench_sobol", "n": n, "n_evaluations": res.n_evaluations,
        "model": args.model or f"paper architecture, {args.members} member(s), trained 1 "
                               "epoch on synthetic_dataset(64)",
        "members": int(getattr(m, "n_members", 1)),
        "wall_time_s": {"sobol_n": t_sobol, "model_evaluation": t_eval,
                        "convergence_study": t_study, "model_load_or_train": t_model},
        "cpu_time_s": {"sobol_n": c_sobol, "model_evaluation": c_eval,
                       "note": "process CPU time, all threads (wall time depends on load)"},
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "cpu_count": os.cpu_count(),
        "target_s": 30.0, "meets_target": t_sobol < 30.0,
        "max_ci_half_width": res.max_conf(),
        "convergence": [{"n": r["n"], "max_conf": r["max_conf"],
                         "elapsed_s": r["elapsed_s"]} for r in rows],
        "threads": torch.get_num_threads(), "python": platform.python_version(),
        "torch": torch.__version__, "machine": platform.machine(),
        "processor": platform.processor() or platform.platform(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    atomic_write_json(args.out, out)
    print(f"Sobol N = {n} ({res.n_evaluations} evaluations, {out['members']} member(s)): "
          f"{t_sobol:.1f} s wall, {c_sobol:.1f} s CPU (model evaluation {t_eval:.1f} s); "
          f"convergence study "
          f"{t_study if t_study is None else round(t_study, 1)} s; wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

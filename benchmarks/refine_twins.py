"""Posterior-guided refinement on synthetic twins: does spending DEM runs near the posterior
narrow the intervals without losing the truth?

Each twin is a dataset row the surrogate never trained on (by default one replicate run of
each replicate group, at a seed neither the training runs nor the new runs use, so its bed
is unseen), whose true parameters are known. For each, ``inverse refine`` runs rounds of
``--batch`` DEM runs up to ``--budget`` (:mod:`inverse.refine`); round 0 is the one-shot
calibration with the initial surrogate. The report compares, per round, the 90 % interval
widths (unit range), the optimum's error and the coverage of the truths over the twins.

    python benchmarks/refine_twins.py run --model models/reference/ensemble.pt \\
        --dataset data/reference.h5 --out studies/refine --budget 12 --batch 4
    python benchmarks/refine_twins.py report --out studies/refine

``run`` is resumable (rerun it; each twin's refinement resumes where it stopped). ``report``
writes ``benchmarks/results/refine_twins.json`` and ``.md`` from the twins' ``refine.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from calendaring import read_dataset, write_json, write_text

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def default_twins(ds) -> list[int]:
    """One replicate row per replicate group, seeds 1, 2, 3, ... (never the training seed)."""
    rows = []
    train_seeds = set(np.unique(ds.seed[ds.role == "train"]).tolist())
    for k, g in enumerate(sorted(set(ds.group[ds.role == "replicate"].tolist()))):
        cand = [i for i in np.nonzero((ds.role == "replicate") & (ds.group == g))[0]
                if ds.seed[i] not in train_seeds]
        if cand:
            rows.append(int(cand[min(k, len(cand) - 1)]))
    return rows


def cmd_run(args) -> int:
    from inverse.optimise import OptimiserConfig
    from inverse.posterior import PosteriorConfig
    from inverse.refine import RefineConfig, refine

    torch.set_num_threads(args.threads)  # a small network: one thread is fastest
    ds = read_dataset(args.dataset)
    rows = args.rows or default_twins(ds)
    out = Path(args.out)
    for n, row in enumerate(rows):
        print(f"[twins] twin {n + 1}/{len(rows)}: row {row} ({ds.run_id[row]})",
              file=sys.stderr, flush=True)
        refine(args.model, args.dataset, out / f"twin-row{row:04d}", target_row=row,
               cfg=RefineConfig(budget=args.budget, batch=args.batch, tol=args.tol,
                                seed=args.seed, workers=args.workers, epochs=args.epochs),
               optimiser=OptimiserConfig(seed=args.seed),
               posterior=PosteriorConfig(seed=args.seed, steps=args.steps, burn=args.burn),
               progress=True)
    return cmd_report(args)


def cmd_report(args) -> int:
    out = Path(args.out)
    twins = []
    for p in sorted(out.glob("twin-row*/refine.json")):
        twins.append(json.loads(p.read_text()))
    if not twins:
        print(f"no twin folders with refine.json under {out}", file=sys.stderr)
        return 2
    names = list(twins[0]["rounds"][0]["posterior"])
    n_rounds = min(len(t["rounds"]) for t in twins)
    per_round = []
    for r in range(n_rounds):
        recs = [t["rounds"][r] for t in twins]
        row = {"round": r, "runs_done_mean": float(np.mean([
            sum(t["rounds"][k]["runs_done"] for k in range(r + 1)) for t in twins])),
               "model_error_sigma_mean": float(np.mean([x["model_error_sigma"] for x in recs])),
               "mean_width_unit": float(np.mean([x["mean_width_unit"] for x in recs])),
               "width_unit": {n: float(np.mean([x["posterior"][n]["width_unit"] for x in recs]))
                              for n in names},
               "coverage": {n: float(np.mean([x["truth"][n]["inside_ci90"] for x in recs]))
                            for n in names},
               "abs_optimum_error_unit": {n: float(np.mean([
                   abs(x["truth"][n]["optimum_error_unit"]) for x in recs])) for n in names}}
        e = [x["error_before_training"]["pressure_rmse_normalised"] for x in recs
             if x.get("error_before_training")]
        row["out_of_sample_rmse_mean"] = float(np.mean(e)) if e else None
        per_round.append(row)
    rep = {"twins": [{"target": t["request"]["target"], "stop_reason": t["stop_reason"],
                      "runs_done": t["runs_done"],
                      "rounds": len(t["rounds"])} for t in twins],
           "model": twins[0]["request"]["model"], "dataset": twins[0]["request"]["dataset"],
           "config": twins[0]["request"]["config"], "per_round": per_round}
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / "refine_twins.json", rep)
    lines = [f"# Refinement on {len(twins)} synthetic twins", "",
             "| round | runs (mean) | sigma | out-of-sample RMSE | mean 90 % width | "
             + " | ".join(names) + " |", "|" + "---|" * (5 + len(names))]
    for row in per_round:
        oos = f"{row['out_of_sample_rmse_mean']:.4f}" if row["out_of_sample_rmse_mean"] \
            else "-"
        cells = [f"{row['width_unit'][n]:.2f} ({100 * row['coverage'][n]:.0f} %)"
                 for n in names]
        lines.append(f"| {row['round']} | {row['runs_done_mean']:.0f} | "
                     f"{row['model_error_sigma_mean']:.4f} | {oos} | "
                     f"{row['mean_width_unit']:.3f} | " + " | ".join(cells) + " |")
    lines += ["", "Cells: mean 90 % interval width (unit range) over the twins, and in "
              "brackets the share of twins whose truth lies inside."]
    write_text(RESULTS / "refine_twins.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("--model", required=True)
    r.add_argument("--dataset", required=True)
    r.add_argument("--out", required=True)
    r.add_argument("--rows", type=int, nargs="+", help="twin rows (default: one replicate "
                                                       "run per group at an unseen seed)")
    r.add_argument("--budget", type=int, default=12)
    r.add_argument("--batch", type=int, default=4)
    r.add_argument("--tol", type=float, default=0.02)
    r.add_argument("--epochs", type=int, default=None)
    r.add_argument("--steps", type=int, default=3000)
    r.add_argument("--burn", type=int, default=1000)
    r.add_argument("--workers", type=int, default=1)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p = sub.add_parser("report")
    p.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    return {"run": cmd_run, "report": cmd_report}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())

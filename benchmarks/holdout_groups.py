"""Where two surrogates miss the held-out seed means: per held-out group, the pressure MSE
(normalised, each model's own normalisation), its signed error over the four quarters of
the stroke, the distance to the nearest training point and to the box's faces (unit
cube), and the ensemble's own spread against its error.

    python benchmarks/holdout_groups.py --dataset data/rve.h5 \\
        --models models/rve/ensemble.pt models/rve/ensemble-gp.pt \\
        --out benchmarks/results/holdout_groups_rve.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def group_errors(model, means) -> dict:
    """Per held-out group: MSE, signed error per stroke quarter, predicted spread."""
    y = model.normalise_pressure(means.pressure)
    pred = model.predict_unit(means.unit_params)
    r = pred.pressure_normalised - y  # (groups, depths)
    q = np.array_split(np.arange(r.shape[1]), 4)
    spread = (np.sqrt(pred.pressure_normalised_var).mean(axis=1)
              if pred.pressure_normalised_var is not None else np.full(len(r), np.nan))
    return {"mse": (r**2).mean(axis=1), "rms": np.sqrt((r**2).mean(axis=1)),
            "quarters": np.stack([r[:, k].mean(axis=1) for k in q], axis=1),
            "mse_by_quarter": [float((r[:, k] ** 2).mean()) for k in q],
            "spread": spread}


def main(argv=None) -> int:
    import surrogate
    from calendaring import read_dataset, seed_means, write_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=str(ROOT / "data" / "rve.h5"))
    ap.add_argument("--models", nargs="+", required=True)
    ap.add_argument("--out", default=None, help="JSON report (default: print only)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    ds = read_dataset(args.dataset)
    means = seed_means(ds, "holdout")
    u = means.unit_params
    train = ds.unit_params[ds.role == "train"]
    nearest = np.min(np.linalg.norm(u[:, None] - train[None], axis=2), axis=1)
    face = np.min(np.minimum(u, 1 - u), axis=1)
    report = {"dataset": args.dataset, "groups": len(u), "models": {}}
    for path in args.models:
        e = group_errors(surrogate.load(path), means)
        name = Path(path).stem
        report["models"][name] = {
            "path": path, "mse_mean": float(e["mse"].mean()),
            "mse_by_quarter": e["mse_by_quarter"],
            "worst_group_share": float(e["mse"].max() / e["mse"].sum()),
            "spread_over_rms_median": float(np.nanmedian(e["spread"] / e["rms"])),
            "per_group": [{"group": int(g), "mse": float(e["mse"][g]),
                           "signed_error_by_quarter": e["quarters"][g].round(4).tolist(),
                           "spread": float(e["spread"][g]), "rms": float(e["rms"][g])}
                          for g in range(len(u))]}
        print(f"{name}: mean MSE {e['mse'].mean():.3g}; by stroke quarter "
              + " / ".join(f"{m:.2g}" for m in e["mse_by_quarter"])
              + f"; worst group {int(e['mse'].argmax())} holds "
              f"{100 * e['mse'].max() / e['mse'].sum():.0f} % of the sum")
        print("  group   MSE      rms    spread  nearest-train  to-face   signed error by "
              "quarter")
        for g in np.argsort(-e["mse"]):
            print(f"  {g:5d} {e['mse'][g]:.2e} {e['rms'][g]:.4f} {e['spread'][g]:.4f} "
                  f"{nearest[g]:13.3f} {face[g]:9.3f}   "
                  + " ".join(f"{x:+.3f}" for x in e["quarters"][g]))
    report["nearest_training_point"] = nearest.round(4).tolist()
    report["distance_to_face"] = face.round(4).tolist()
    report["unit_params"] = {n: u[:, j].round(4).tolist() for j, n in enumerate(ds.space.names)}
    if args.out:
        write_json(args.out, report)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""How tortuosity converges in the voxel size, on lateral windows of one snapshot.

The refinement of ``analysis.microstructure.converge_snapshot`` runs on the whole periodic
cell, where a 100 um snapshot reaches its voxel budget at 6.8 voxels per 2 um. This script
takes a W x W um window of the snapshot (full thickness) and refines it further, with the
same partial-volume voxels (3^3 sub-voxels) and ``solve_tortuosity(..., periodic=False)``
(TauFactor's MultiPhaseSolver, no-flux side walls), to see how tau behaves below the whole
cell's finest voxel: the level-to-level changes, the observed order and what a 2 %
stopping rule would report.

The window is voxelised as a periodic box of W + 2 m (m: the largest radius and a voxel)
holding every sphere (and periodic image) whose centre lies within m of the window, then
cropped to the window, so no sphere wraps into it. Lengths SI; writes JSON atomically.

    python benchmarks/microstructure_windows.py RUN.h5 --snapshot 1 --window 20 \\
        --origin 10 10 --levels 4.5 6.76 10.12 15.2 --out benchmarks/results/windows.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np


def window_spheres(snap, cell_x, cell_y, x0, y0, width, margin):
    """Centres (shifted so the window starts at ``margin``) and radii of the spheres and
    periodic images whose centres lie within ``margin`` of the window."""
    pos, rad = [], []
    for dx in (-cell_x, 0.0, cell_x):
        for dy in (-cell_y, 0.0, cell_y):
            q = snap.position + np.array([dx, dy, 0.0])
            sel = ((q[:, 0] >= x0 - margin) & (q[:, 0] < x0 + width + margin)
                   & (q[:, 1] >= y0 - margin) & (q[:, 1] < y0 + width + margin))
            pos.append(q[sel])
            rad.append(snap.radius[sel])
    pos = np.concatenate(pos)
    pos[:, 0] -= x0 - margin
    pos[:, 1] -= y0 - margin
    return pos, np.concatenate(rad)


def solve_window(snap, cell_x, cell_y, x0, y0, width, vpd, d_ref, tol):
    from analysis.microstructure import solve_tortuosity, voxelise

    n = max(2, round(width * vpd / d_ref))
    h = width / n
    k = int(np.ceil(snap.radius.max() / h)) + 1  # margin in voxels
    pos, rad = window_spheres(snap, cell_x, cell_y, x0, y0, width, k * h)
    t0 = time.perf_counter()
    box = width + 2 * k * h
    img = voxelise(pos, rad, np.zeros(len(rad)), box, box, snap.z_bottom, snap.z_top, h,
                   supersample=3)[:, k:k + n, k:k + n]
    tv = time.perf_counter() - t0
    tr = solve_tortuosity(img, device="cpu", tol=tol, iter_limit=40_000, periodic=False)
    return {"voxels_per_diameter": d_ref / h, "voxel_size_m": h, "shape_zyx": list(img.shape),
            "voxels": int(img.size), "voxel_porosity": float(img.mean(dtype=np.float64)),
            "tortuosity": tr.tortuosity, "D_eff": tr.D_eff, "iterations": tr.iterations,
            "solver_converged": tr.converged, "solver": tr.solver, "voxelise_seconds": tv,
            "solve_seconds": tr.seconds}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="run file")
    ap.add_argument("--snapshot", type=int, default=-1, help="snapshot index")
    ap.add_argument("--window", type=float, default=20.0, help="window edge [um]")
    ap.add_argument("--origin", type=float, nargs=2, default=[10.0, 10.0],
                    help="window corner x y [um]")
    ap.add_argument("--levels", type=float, nargs="+", default=[4.5, 6.76, 10.12, 15.2],
                    help="voxels per smallest diameter")
    ap.add_argument("--tol", type=float, default=1e-3, help="TauFactor tolerance")
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" /
                                         "microstructure_windows.json"))
    args = ap.parse_args(argv)
    import torch

    from analysis.microstructure import reference_diameter
    from calendaring import read_run, write_json

    torch.set_num_threads(args.threads)
    rec = read_run(args.run)
    snap = rec.snapshots[args.snapshot]
    d_ref = reference_diameter(rec.config)
    width, x0, y0 = args.window * 1e-6, args.origin[0] * 1e-6, args.origin[1] * 1e-6
    if not (0 < width <= min(rec.cell_x, rec.cell_y)):
        raise SystemExit(f"--window = {args.window} um: allowed (0, {rec.cell_x * 1e6:g}]")
    rows = []
    report = {"benchmark": "microstructure_windows", "run": str(args.run),
              "snapshot": int(snap.index), "depth_m": float(snap.depth),
              "window_m": width, "origin_m": [x0, y0], "reference_diameter_m": d_ref,
              "cell_m": [rec.cell_x, rec.cell_y], "torch_threads": args.threads,
              "load_average_start": os.getloadavg(), "levels": rows}
    for vpd in args.levels:
        row = solve_window(snap, rec.cell_x, rec.cell_y, x0, y0, width, vpd, d_ref, args.tol)
        if rows:
            row["tortuosity_rel_change"] = abs(row["tortuosity"] - rows[-1]["tortuosity"]) \
                / row["tortuosity"]
        rows.append(row)
        print(f"{row['voxels_per_diameter']:6.2f} vox/d {row['voxels']:>11,} voxels: porosity "
              f"{row['voxel_porosity']:.4f} tau {row['tortuosity']:.4f} "
              f"change {row.get('tortuosity_rel_change', float('nan')):.4f} "
              f"({row['iterations']} iterations, {row['solve_seconds']:.0f} s)",
              file=sys.stderr, flush=True)
    if len(rows) >= 3:  # observed order from successive differences (levels ~ x1.5)
        t = np.array([r["tortuosity"] for r in rows])
        h = np.array([r["voxel_size_m"] for r in rows])
        d = -np.diff(t)
        with np.errstate(divide="ignore", invalid="ignore"):
            report["observed_order"] = (np.log(d[:-1] / d[1:]) / np.log(h[:-2] / h[1:-1])
                                        ).tolist()
    report["load_average_end"] = os.getloadavg()
    write_json(Path(args.out), report, indent=2)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

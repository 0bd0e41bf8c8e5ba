"""Voxels per second of ``analysis.microstructure.voxelise`` and the wall time of the
microstructure analysis of a run's snapshots: by default the resolution-converged one
(partial-volume voxels refined until tau changes by < 2 %; every level's voxel count,
iterations and seconds are recorded), or ``--resolution two-point``.

    python benchmarks/bench_voxelise.py --run RUN.h5          # a run file
    python benchmarks/bench_voxelise.py --run RVE.h5 --analyse 1 --voxels-per-diameter 4 \
        --repeats 3 --out benchmarks/results/bench_voxelise_rve.json   # one 100 um snapshot
    python benchmarks/bench_voxelise.py                       # random packing, no analysis

Voxel throughput is timed on the run's deepest snapshot (or, without ``--run``, on a random
packing of the quick preset's size: 30 x 30 um cell, 55.5 um gap, 130 AM + 330 CB spheres)
at several resolutions, binary and partial-volume; the median and the best of ``--repeats``
calls are recorded (the best is the least disturbed by other work on a shared machine).
Writes JSON atomically (default benchmarks/results/bench_voxelise.json). The load average is
recorded because the machine is shared: compare figures side by side only.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np


def random_packing(seed: int = 0):
    """Centres, radii, materials and the cell of a random packing of a quick run's size."""
    rng = np.random.default_rng(seed)
    cell, gap = 30e-6, 55.5e-6
    d_am = np.clip(rng.normal(7.74e-6, 1.35e-6, 130), 4.94e-6, 10.69e-6)
    rad = np.concatenate([d_am / 2, np.full(330, 1.5e-6)])
    mat = np.concatenate([np.zeros(130, np.int32), np.ones(330, np.int32)])
    pos = rng.uniform([0, 0, 0], [cell, cell, gap], (len(rad), 3))
    return pos, rad, mat, cell, cell, 0.0, gap


def time_voxelise(geometry, voxel_size: float, supersample: int, repeats: int) -> dict:
    from analysis.microstructure import voxelise

    pos, rad, mat, cx, cy, z0, z1 = geometry
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        img = voxelise(pos, rad, mat, cx, cy, z0, z1, voxel_size, supersample=supersample)
        times.append(time.perf_counter() - t)
    med, best = float(np.median(times)), float(np.min(times))
    return {"voxel_size_m": voxel_size, "supersample": supersample,
            "shape_zyx": list(img.shape), "voxels": int(img.size),
            "median_seconds": med, "best_seconds": best, "voxels_per_second": img.size / med,
            "voxels_per_second_best": img.size / best,
            "sub_voxel_tests_per_second": img.size * supersample**3 / med}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", help="quick-preset run file (read with read_run)")
    ap.add_argument("--snapshot", type=int, default=-1, help="snapshot for the voxel timing")
    ap.add_argument("--voxels-per-diameter", type=float, nargs="+", default=[4.0, 5.0, 10.0, 20.0])
    ap.add_argument("--supersample", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--threads", type=int, default=2, help="torch threads (TauFactor)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--no-analysis", action="store_true", help="skip the microstructure timing")
    ap.add_argument("--resolution", default="converge", choices=("converge", "two-point"),
                    help="the microstructure analysis timed (analysis.microstructure)")
    ap.add_argument("--analyse", type=int, nargs="+",
                    help="snapshot indices of the analysis (default: all)")
    ap.add_argument("--max-voxels", type=float, default=40e6,
                    help="largest refinement level (converge)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" /
                                         "bench_voxelise.json"))
    args = ap.parse_args(argv)

    import torch

    from analysis.microstructure import (
        DEFAULT_VOXELS_PER_DIAMETER,
        analyse_run,
        reference_diameter,
        voxel_size_for,
    )

    torch.set_num_threads(args.threads)
    if args.run:
        from calendaring import read_run

        record = read_run(args.run)
        snap = record.snapshots[args.snapshot]
        geometry = (snap.position, snap.radius, snap.material, record.cell_x, record.cell_y,
                    snap.z_bottom, snap.z_top)
        d_ref = reference_diameter(record.config)
        source = f"{args.run} snapshot {snap.index} (depth {snap.depth * 1e6:.1f} um, " \
                 f"{len(snap.radius)} particles)"
    else:
        geometry = random_packing()
        d_ref = 2e-6
        source = "random packing, 460 spheres, 30 x 30 x 55.5 um"
    report = {"benchmark": "bench_voxelise", "source": source, "python": sys.version.split()[0],
              "machine": platform.machine(), "cpu_count": os.cpu_count(),
              "torch_threads": args.threads, "load_average_start": os.getloadavg(),
              "reference_diameter_m": d_ref, "voxelise": []}
    for vpd in args.voxels_per_diameter:
        h = voxel_size_for(geometry[3], d_ref, vpd)
        # partial-volume mode only up to 10 vox/d (x27 sub-voxel tests beyond that)
        for s in (1, args.supersample) if vpd <= 10 else (1,):
            row = time_voxelise(geometry, h, s, args.repeats)
            row["voxels_per_diameter"] = vpd
            report["voxelise"].append(row)
            print(f"voxelise {vpd:5.1f} vox/d x{s}: {row['shape_zyx']} "
                  f"{row['voxels_per_second']:.3g} voxels/s (median; best "
                  f"{row['voxels_per_second_best']:.3g}) "
                  f"({row['sub_voxel_tests_per_second']:.3g} sub-voxel tests/s)", file=sys.stderr)
    if args.run and not args.no_analysis:
        t0, c0 = time.perf_counter(), time.process_time()
        res = analyse_run(args.run, snapshots=args.analyse, device=args.device,
                          progress=True, resolution=args.resolution,
                          max_voxels=args.max_voxels)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        snaps = res.to_json()["snapshots"]

        def detail(s):
            if s["refinement"] is not None:
                return {"refinement": s["refinement"], "porosities": s["porosities"]}
            return {"second": {k: s["second_resolution"][k] for k in
                               ("voxel_porosity", "tortuosity", "D_eff", "shape_zyx",
                                "iterations", "solve_seconds")},
                    "extrapolated": s["extrapolated"], "porosities": s["porosities"]}

        report["microstructure"] = {
            "settings": res.settings, "default_voxels_per_diameter":
            DEFAULT_VOXELS_PER_DIAMETER, "snapshots": len(snaps), "wall_seconds": wall,
            "process_cpu_seconds": cpu,
            "per_snapshot": [{k: s[k] for k in ("depth_m", "particle_porosity",
                                                "voxel_porosity", "tortuosity", "D_eff",
                                                "shape_zyx", "iterations", "solve_seconds",
                                                "voxelise_seconds")} | detail(s)
                             for s in snaps]}
        print(f"microstructure of {len(snaps)} snapshots: {wall:.1f} s wall, "
              f"{cpu:.1f} s CPU", file=sys.stderr)
    report["load_average_end"] = os.getloadavg()
    out = Path(args.out)
    from calendaring import write_json

    write_json(out, report, indent=2)  # atomic; NaN -> null
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

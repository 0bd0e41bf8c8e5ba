"""The production run, timed whole and by phase: ``calendaring run --preset sweep`` exactly as
a sweep task starts it.

For each cell size (``--cells``, in micrometres) a settled bed is made once by ``calendaring
pack`` (untimed, as a sweep makes one bed per seed; kept in ``--bed-dir``), then one
process runs ``python -m calendaring.cli run --preset sweep`` from it on ``--threads``
threads at the Table 4 parameters, and its wall time is measured from outside. The run
file's ``info.phases`` (see ``Simulation.phase``) splits it into the engine's time steps
(``steps``: the kernel launches of the pre-compaction, relaxation and calendering),
neighbour rebuilds, breakage replacements (without their rebuilds), records and snapshots,
checkpoints, host checks, the plate trace and set-up; what is left of the process wall
time is start-up (Python imports, Taichi's kernel compilation or cache load) and the file
write. Reported per cell: particles at start and end, breakage events, calendering steps,
particle-steps of the calendering (the sum over its steps of the live particles), and
particle-steps/s per thread over the whole process, over the calendering stage and within
the engine's steps alone (the rate the host-side work leaves on the table).

    python benchmarks/bench_production.py --cells 30 70 100
    python benchmarks/bench_production.py --cells 100 --set numerics.skin=0.6e-6

Writes JSON (default benchmarks/results/bench_production.json). Speed is measured here,
never asserted in tests.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "calendaring.cli", *args]


def ensure_bed(folder: Path, cell_um: float, seed: int, threads: int,
               overrides: list[str]) -> Path:
    """The settled bed of the sweep preset in a ``cell_um`` cell (made once, untimed)."""
    path = folder / f"bed-{cell_um:g}um-s{seed}.csv"
    if not path.exists():
        cmd = _cli("pack", "--preset", "sweep", "--seed", str(seed), "--threads", str(threads),
                   "--quiet", "--out", str(path), *cell_sets(cell_um), *overrides)
        subprocess.run(cmd, check=True)
    return path


def cell_sets(cell_um: float) -> list[str]:
    side = f"{cell_um * 1e-6:.6g}"
    return ["--set", f"domain.cell_x={side}", "--set", f"domain.cell_y={side}"]


def particle_steps(series: dict) -> float:
    """Sum over the calendering steps of the live particles (each record row's count held
    over the steps since the previous row)."""
    steps = np.asarray(series["step"], float)
    n = np.asarray(series["particles"], float)
    if len(steps) < 2:
        return 0.0
    return float(np.sum(np.diff(steps) * n[1:]))


def run_once(bed: Path, cell_um: float, seed: int, threads: int, overrides: list[str],
             folder: Path) -> dict:
    from calendaring import read_run

    out = folder / f"run-{cell_um:g}um-s{seed}.h5"
    cmd = _cli("run", "--preset", "sweep", "--seed", str(seed), "--threads", str(threads),
               "--quiet", "--overwrite", "--out", str(out),
               "--set", f'electrode.packing="{bed}"', *cell_sets(cell_um), *overrides)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = time.perf_counter() - t0
    rec = read_run(out)
    info = rec.info
    phases = info.get("phases", {})
    booked = sum(p["seconds"] for p in phases.values())
    cal = info["stages"]["calender"]
    ps = particle_steps(rec.series)
    result = {
        "cell_um": cell_um, "seed": seed, "threads": threads, "overrides": overrides,
        "process_wall_s": wall, "run_wall_s": info["wall_seconds"],
        "particles_at_start": info["n_particles"],
        "particles_at_end": int(rec.series["particles"][-1]),
        "breakage_events": info["breakage_events"], "bonds": info.get("bonds_created"),
        "calender_steps": cal["steps"], "calender_wall_s": cal["wall_seconds"],
        "stages": info["stages"],
        "phases": {k: {**v, "ms_per_call": 1e3 * v["seconds"] / max(1, v["calls"]),
                       "fraction_of_process": v["seconds"] / wall}
                   for k, v in sorted(phases.items(), key=lambda kv: -kv[1]["seconds"])},
        "startup_and_write_s": wall - booked,
        "calender_particle_steps": ps,
        "particle_steps_per_s_calender": ps / cal["wall_seconds"],
        "pressure_at_end_Pa": float(rec.pressure["value"][-1]),
    }
    out.unlink(missing_ok=True)
    return result


def report(r: dict) -> str:
    lines = [f"[production] {r['cell_um']:g} um, seed {r['seed']}, {r['threads']} thread(s): "
             f"{r['process_wall_s']:.1f} s process, calendering {r['calender_steps']} steps in "
             f"{r['calender_wall_s']:.1f} s = {r['particle_steps_per_s_calender']:.3g} "
             f"particle-steps/s; particles {r['particles_at_start']} -> "
             f"{r['particles_at_end']}, {r['breakage_events']} events"]
    for k, v in r["phases"].items():
        lines.append(f"    {k:11s} {v['seconds']:8.1f} s {v['calls']:7d} calls "
                     f"{v['ms_per_call']:9.2f} ms/call {100 * v['fraction_of_process']:5.1f} %")
    lines.append(f"    {'start-up+write':11s} {r['startup_and_write_s']:8.1f} s")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=float, nargs="+", default=[30.0, 70.0, 100.0],
                    help="cell sides [um]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--set", dest="overrides", action="append", default=[],
                    metavar="KEY=VALUE", help="config override for the runs (not the beds)")
    ap.add_argument("--bed-dir", default=None, help="keep the settled beds here")
    ap.add_argument("--out", default=str(RESULTS / "bench_production.json"))
    args = ap.parse_args(argv)
    beds = Path(args.bed_dir) if args.bed_dir else Path(tempfile.mkdtemp(prefix="beds-"))
    beds.mkdir(parents=True, exist_ok=True)
    sets = [x for kv in args.overrides for x in ("--set", kv)]
    runs = []
    with tempfile.TemporaryDirectory(prefix="production-") as tmp:
        for cell in args.cells:
            bed = ensure_bed(beds, cell, args.seed, args.threads, [])
            r = run_once(bed, cell, args.seed, args.threads, sets, Path(tmp))
            print(report(r), flush=True)
            runs.append(r)
    from bench_dem import _software  # this folder is on sys.path when run as a script

    from calendaring import write_json

    result = {"benchmark": "bench_production", "runs": runs, "software": _software(),
              "python": sys.version.split()[0], "machine": platform.machine(),
              "cpus": os.cpu_count(), "load_average": os.getloadavg(),
              "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    write_json(Path(args.out), result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

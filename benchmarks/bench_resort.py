"""Slot order at the end of a breaking production run, timed from one state both ways.

A sweep-preset run (the production run of ``bench_production.py``: the same bed, cell and
parameters) calenders with ``numerics.resort_fraction = 0``, so the fragments of every
breakage event pile up at the tail of the pool and the dead parents keep their slots. At
the end of the stroke the run's state is kept and the plate held still. From that state,
``--steps`` steps are timed (after a warm-up that also absorbs any kernel compilation):

- ``as_left``: in the slot order the run left;
- ``resorted``: the same state after ``Simulation.resort`` (live particles along the
  space-filling curve, dead slots dropped);
- ``as_left`` once more, to bound the drift of the machine's speed over the measurement.

Both start from the same positions, so they do the same work up to round-off (the same
contacts; breakage is switched off for the timing, so no event falls into one and not the
other). Reported: steps/s and particle-steps/s of each, the resort's own wall time, and a
locality figure of each order (the median slot distance of the candidate pairs).

    python benchmarks/bench_resort.py --cell 100 --bed-dir beds/

Writes JSON (default benchmarks/results/bench_resort.json). Speed is measured here, never
asserted in tests.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_production import cell_sets, ensure_bed  # noqa: E402

RESULTS = HERE / "results"


class _Kept(Exception):
    """Raised from the end of the calendering stage once the timings are taken."""


def _pair_gap(sim) -> float:
    t = sim.table
    n = int(t.n_pairs[None])
    owner = t.owner.to_numpy()[:n]
    partner = t.partner.to_numpy()[:n]
    return float(np.median(np.abs(partner.astype(np.int64) - owner)))


def _time_steps(sim, steps: int, warmup: int) -> dict:
    sim.run(warmup)
    n_alive = sim.pool.n_alive()
    t0 = time.perf_counter()
    sim.run(steps)
    wall = time.perf_counter() - t0
    return {"steps": steps, "wall_s": wall, "steps_per_s": steps / wall,
            "particle_steps_per_s": steps * n_alive / wall, "particles": n_alive,
            "slots_used": sim.pool.slots_used, "median_pair_slot_gap": _pair_gap(sim)}


def measure(cfg, steps: int, warmup: int) -> dict:
    from calendaring import CalenderRun

    out: dict = {}

    class Run(CalenderRun):
        def _finish_calender(self) -> None:
            super()._finish_calender()
            sim = self.sim
            sim.set_top_plate(velocity=0.0)
            self._take_breakage()  # the run's records; save_state wants none pending
            sim.breakage_active = False  # the same work in every timing: no new events
            out["events"] = int(sim.n_breakage_events)
            out["particles_at_start"] = int(self.rs.info["n_particles"])
            state = sim.save_state()
            out["as_left"] = _time_steps(sim, steps, warmup)
            sim.load_state(state)
            sim.breakage_active = False
            t0 = time.perf_counter()
            sim.resort()
            out["resort_s"] = time.perf_counter() - t0
            out["resorted"] = _time_steps(sim, steps, warmup)
            sim.load_state(state)
            sim.breakage_active = False
            out["as_left_again"] = _time_steps(sim, steps, warmup)
            raise _Kept

    with tempfile.TemporaryDirectory(prefix="resort-") as tmp:
        try:
            Run(cfg, Path(tmp) / "run.h5", progress=False, preset="sweep").execute()
        except _Kept:
            pass
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cell", type=float, default=100.0, help="cell side [um]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--steps", type=int, default=5000, help="timed steps per order")
    ap.add_argument("--warmup", type=int, default=500)
    ap.add_argument("--bed-dir", default=None, help="keep the settled beds here")
    ap.add_argument("--out", default=str(RESULTS / "bench_resort.json"))
    args = ap.parse_args(argv)

    import json

    from calendaring import load_preset, parse_override, with_overrides

    beds = Path(args.bed_dir) if args.bed_dir else Path(tempfile.mkdtemp(prefix="beds-"))
    beds.mkdir(parents=True, exist_ok=True)
    bed = ensure_bed(beds, args.cell, args.seed, args.threads, [])
    sets = [*cell_sets(args.cell)[1::2], f'electrode.packing="{bed}"',
            f"numerics.seed={args.seed}", f"numerics.threads={args.threads}",
            "numerics.resort_fraction=0"]
    cfg = with_overrides(load_preset("sweep"), dict(parse_override(s) for s in sets))
    t0 = time.perf_counter()
    res = measure(cfg, args.steps, args.warmup)
    a, b, c = res["as_left"], res["resorted"], res["as_left_again"]
    res.update({
        "benchmark": "bench_resort", "cell_um": args.cell, "seed": args.seed,
        "threads": args.threads, "speedup": b["steps_per_s"] / (0.5 * (a["steps_per_s"]
                                                                         + c["steps_per_s"])),
        "total_wall_s": time.perf_counter() - t0, "python": platform.python_version(),
        "machine": platform.machine(), "cpus": os.cpu_count(),
        "load_average": list(os.getloadavg()),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    })
    for name in ("as_left", "resorted", "as_left_again"):
        r = res[name]
        print(f"[resort] {name:13s} {r['steps_per_s']:8.1f} steps/s "
              f"{r['particle_steps_per_s']:.3g} particle-steps/s, {r['slots_used']} slots for "
              f"{r['particles']} particles, median pair slot gap {r['median_pair_slot_gap']:.0f}")
    print(f"[resort] resort {1e3 * res['resort_s']:.0f} ms; speed-up {res['speedup']:.3f}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(args.out).with_suffix(".json.tmp")
    tmp.write_text(json.dumps(res, indent=2))
    tmp.replace(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

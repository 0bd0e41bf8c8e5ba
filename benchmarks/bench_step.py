"""Particle-steps per second of the DEM engine on a bed loaded by the top plate.

Builds an AM/CB bed (default 1,440 AM + 3,700 CB in a 100 x 100 um cell, as the LIGGGHTS
reference input ../shared/bench/liggghts-compaction.in), pre-compacts it with a coarse step
(untimed), then times ``--steps`` steps at the paper's 4 % Rayleigh time step with the top
plate moving down at ``--speed``. Writes JSON (default benchmarks/results/bench_step.json).

    python benchmarks/bench_step.py --threads 2
    python benchmarks/bench_step.py --model hertz      # the Hertz-Mindlin reduction
    python benchmarks/bench_step.py --breakage off     # without the breakage bookkeeping

Speed targets are checked here, never in tests.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np


def prepare_dense_bed(cfg, n_am: int, n_cb: int, porosity: float, seed: int = 0,
                      prep_speed: float = 5.0):
    """Random loose bed of ``n_am`` + ``n_cb`` spheres from the size distributions of
    ``cfg``, pre-compacted to ``porosity`` (see :func:`compact_bed`)."""
    from calendaring import sample_diameters

    rng = np.random.default_rng(seed)
    sizes = cfg.electrode.sizes
    diam = np.concatenate([sample_diameters(sizes["AM"], rng, n_am),
                           sample_diameters(sizes["CB"], rng, n_cb)])
    mat = np.concatenate([np.zeros(n_am, np.int32), np.ones(n_cb, np.int32)])
    return compact_bed(cfg, diam, mat, porosity, rng, prep_speed)


def compact_bed(cfg, diam, mat, porosity: float, rng, prep_speed: float = 5.0,
                hold_steps: int = 0):
    """Random sequential insertion of the spheres ``diam`` (materials ``mat``) in a column
    three times the dense height, then pre-compaction by the top plate at ``prep_speed``
    with a coarse (20 %) Rayleigh step down to ``porosity``, breakage off (untimed); then
    ``hold_steps`` steps with the plate held, so that the bed comes to rest under load.

    Returns (positions, radii, materials, velocities, plate height).
    """
    from calendaring import Simulation, random_insertion, with_overrides

    area = cfg.domain.cell_x * cfg.domain.cell_y
    z_dense = max((np.pi / 6) * np.sum(diam**3) / area / (1.0 - porosity), 1.5 * diam.max())
    z_insert = max(3.0 * z_dense, 2.5 * float(diam.max()))
    pos, rad, mat = random_insertion(diam, mat, cfg.domain.cell_x, cfg.domain.cell_y,
                                     z_insert, rng)
    # the fast, coarse pre-compaction can shoot a squeezed carbon-black sphere out at tens
    # of m/s; a wider skin (at least 1 um) keeps its neighbour list valid (untimed stage)
    prep = with_overrides(cfg, {"numerics.timestep_fraction": 0.2,
                                "numerics.rebuild_check_interval": 1,
                                "numerics.skin": max(cfg.numerics.skin, 1e-6),
                                "breakage.enabled": False,
                                "domain.height": max(cfg.domain.height, z_insert + 1e-6)})
    sim = Simulation(prep, capacity=len(rad))
    try:
        sim.add_particles(pos, rad, mat)
        sim.prime()
        z0 = z_insert + 0.5e-6
        n = int(np.ceil((z0 - z_dense) / (prep_speed * sim.dt)))
        sim.set_top_plate_history([0.0, n * sim.dt], [z0, z_dense])
        sim.run(n)
        if hold_steps:
            sim.set_top_plate(z=z_dense, velocity=0.0)
            sim.run(hold_steps)
        s = sim.state()
        return s["position"], s["radius"], s["material"], s["velocity"], sim.z_top
    finally:
        sim.destroy()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-am", type=int, default=1440)
    ap.add_argument("--n-cb", type=int, default=3700)
    ap.add_argument("--cell", type=float, default=100e-6, help="periodic cell edge [m]")
    ap.add_argument("--porosity", type=float, default=0.5, help="porosity after pre-compaction")
    ap.add_argument("--steps", type=int, default=5000, help="timed steps")
    ap.add_argument("--speed", type=float, default=0.05, help="top-plate speed [m/s]")
    ap.add_argument("--prep-speed", type=float, default=5.0, help="pre-compaction speed [m/s]")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--model", choices=("eepa", "hertz"), default="eepa")
    ap.add_argument("--no-energy", action="store_true", help="switch the energy ledger off")
    ap.add_argument("--breakage", choices=("on", "off"), default="on",
                    help="Tavares breakage (stressing energy, events, damage) on or off")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "bench_step.json"))
    args = ap.parse_args(argv)

    from calendaring import SimConfig, Simulation, with_overrides

    over = {"domain.cell_x": args.cell, "domain.cell_y": args.cell,
            "numerics.threads": args.threads, "numerics.track_energy": not args.no_energy,
            "breakage.enabled": args.breakage == "on"}
    cfg = with_overrides(SimConfig(), over)
    if args.model == "hertz":
        for key in ("AM-AM", "AM-CB", "CB-CB"):
            over[f"contact.pairs.{key}.plasticity_ratio"] = 0.0
            over[f"contact.pairs.{key}.surface_energy"] = 0.0
        for key in ("AM", "CB"):
            over[f"contact.plate_pairs.{key}.plasticity_ratio"] = 0.0
        over["contact.tangential_stiffness_ratio"] = 1.0
        cfg = with_overrides(SimConfig(), over)

    t0 = time.perf_counter()
    pos, rad, mat, vel, z_top = prepare_dense_bed(cfg, args.n_am, args.n_cb, args.porosity, 0,
                                                  prep_speed=args.prep_speed)
    t_prep = time.perf_counter() - t0
    from calendaring import pool_capacity

    sim = Simulation(cfg, capacity=pool_capacity(cfg, rad, mat))
    try:
        sim.add_particles(pos, rad, mat, velocity=vel)
        sim.set_top_plate(z=z_top, velocity=-args.speed)
        t0 = time.perf_counter()
        sim.run(1)  # compile (or load from the offline cache) and prime
        t_start = time.perf_counter() - t0
        sim.run(200)  # warm-up
        rebuilds0 = sim.n_rebuilds
        t0 = time.perf_counter()
        sim.run(args.steps)
        wall = time.perf_counter() - t0
        n = sim.pool.n_alive()
        s = sim.state()
        contacts = float(np.mean(s["n_contacts"]))
        result = {
            "benchmark": "bench_step",
            "model": args.model,
            "particles": n,
            "n_am": int(np.sum(s["material"] == 0)),
            "n_cb": int(np.sum(s["material"] == 1)),
            "threads": args.threads,
            "steps": args.steps,
            "wall_s": wall,
            "steps_per_s": args.steps / wall,
            "particle_steps_per_s": n * args.steps / wall,
            "dt_s": sim.dt,
            "mean_contacts_per_particle": contacts,
            "rebuilds": sim.n_rebuilds - rebuilds0,
            "top_pressure_Pa": sim.top_pressure(),
            "track_energy": not args.no_energy,
            "breakage": args.breakage,
            "breakage_events": sim.n_breakage_events,
            "first_step_s": t_start,
            "prep_s": t_prep,
            "python": sys.version.split()[0],
            "machine": platform.machine(),
            "processor": platform.processor(),
        }
    finally:
        sim.destroy()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2))
    tmp.replace(out)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A loose AM/CB bed compacted by the top plate: the engine's end-to-end demonstration.

This is the main job until the electrode builder, bonds and breakage land (issues 3 and 4):
it inserts non-overlapping NMC622 (AM) and carbon-black (CB) spheres with the paper's size
distributions, pre-compacts them quickly with a coarse time step, then compresses the bed at
the paper's 4 % Rayleigh time step and records the top-plate pressure against the plate
displacement. Outputs: ``pressure.csv`` (SI units in the header), ``pressure.png`` and
``summary.json``.

    python -m calendaring.demo --out out/demo
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from calendaring.config import SimConfig, with_overrides
from calendaring.units import to_mpa, to_um

AM_MEAN, AM_SD, AM_MIN, AM_MAX = 7.74e-6, 1.35e-6, 4.94e-6, 10.69e-6  # diameters [m], paper
CB_DIAMETER = 3.0e-6  # [m], paper


def sample_diameters(rng: np.random.Generator, n_am: int, n_cb: int) -> tuple[np.ndarray, np.ndarray]:
    """AM diameters from N(7.74, 1.35) um capped to [4.94, 10.69] um (resampled), CB 3 um."""
    d = rng.normal(AM_MEAN, AM_SD, size=4 * n_am + 16)
    d = d[(d >= AM_MIN) & (d <= AM_MAX)][:n_am]
    diam = np.concatenate([d, np.full(n_cb, CB_DIAMETER)])
    mat = np.concatenate([np.zeros(n_am, np.int32), np.ones(n_cb, np.int32)])
    return diam, mat


def _overlaps(cells, pos, diam, p, r, c, nx, ny, lx, ly) -> bool:
    """True if a sphere (centre p, radius r, cell c) overlaps one already in ``cells``."""
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                for j in cells.get(((c[0] + dx) % nx, (c[1] + dy) % ny, c[2] + dz), ()):
                    v = pos[j] - p
                    v[0] -= lx * round(v[0] / lx)
                    v[1] -= ly * round(v[1] / ly)
                    if v @ v < (r + 0.5 * diam[j]) ** 2:
                        return True
    return False


def random_bed(cfg: SimConfig, diam: np.ndarray, mat: np.ndarray, z_max: float,
               rng: np.random.Generator, max_tries: int = 200
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random sequential insertion of non-overlapping spheres in [0, L]^2 x [0, z_max].

    Largest spheres first, periodic in x and y, checked against a hashed cell grid.
    Returns (positions [m], radii [m], material indices), largest first.
    """
    order = np.argsort(-diam, kind="stable")
    diam, mat = diam[order], mat[order]
    lx, ly = cfg.domain.cell_x, cfg.domain.cell_y
    h = float(diam.max())
    nx, ny = max(1, int(lx // h)), max(1, int(ly // h))
    cells: dict[tuple[int, int, int], list[int]] = {}
    pos = np.zeros((len(diam), 3))
    for k, d in enumerate(diam):
        r = 0.5 * d
        for _ in range(max_tries):
            p = np.array([rng.uniform(0, lx), rng.uniform(0, ly), rng.uniform(r, z_max - r)])
            c = (int(p[0] / lx * nx) % nx, int(p[1] / ly * ny) % ny, int(p[2] // h))
            if not _overlaps(cells, pos, diam, p, r, c, nx, ny, lx, ly):
                pos[k] = p
                cells.setdefault(c, []).append(k)
                break
        else:
            raise RuntimeError(
                f"could not insert particle {k} of {len(diam)} without overlap in "
                f"{max_tries} tries: raise z_max ({z_max:.3e} m)")
    return pos, 0.5 * diam, mat


def compress(sim, z_end: float, speed: float, n_records: int = 200, progress=None) -> dict:
    """Move the top plate down to ``z_end`` at ``speed`` [m/s]; record pressure vs travel."""
    if not sim._primed:
        sim.prime()
    z0 = sim.z_top
    total = max(1, int(math.ceil((z0 - z_end) / (speed * sim.dt))))
    every = max(1, total // n_records)
    sim.set_top_plate(velocity=-speed)
    travel, top, bottom = [], [], []
    t_start = time.perf_counter()
    done = 0
    while done < total:
        k = min(every, total - done)
        sim.run(k)
        done += k
        travel.append(z0 - sim.z_top)
        top.append(sim.top_pressure())
        bottom.append(sim.bottom_pressure())
        if progress is not None:
            progress(done, total, time.perf_counter() - t_start)
    sim.set_top_plate(velocity=0.0)
    return {"travel": np.array(travel), "top_pressure": np.array(top),
            "bottom_pressure": np.array(bottom), "steps": total,
            "wall": time.perf_counter() - t_start}


def _progress_printer(label: str):
    last = [0.0]

    def show(done, total, elapsed):
        if elapsed - last[0] < 2.0 and done < total:
            return
        last[0] = elapsed
        rate = done / elapsed if elapsed > 0 else 0.0
        eta = (total - done) / rate if rate > 0 else float("nan")
        print(f"  {label}: {done}/{total} steps ({100 * done / total:5.1f} %), "
              f"{rate:7.0f} steps/s, ETA {eta:6.1f} s", flush=True)

    return show


def prepare_dense_bed(cfg: SimConfig, n_am: int, n_cb: int, porosity: float, seed: int = 0,
                      prep_speed: float = 2.0, verbose: bool = True):
    """Insert a loose bed and pre-compact it to the given porosity with a coarse (20 %) step.

    Returns (positions, radii, materials, velocities, plate height) of the pre-compacted bed.
    """
    from calendaring.simulation import Simulation

    rng = np.random.default_rng(seed)
    diam, mat = sample_diameters(rng, n_am, n_cb)
    solid_height = (np.pi / 6) * np.sum(diam**3) / (cfg.domain.cell_x * cfg.domain.cell_y)
    # a bed thinner than its largest sphere would be crushed between the plates
    z_dense = max(solid_height / (1.0 - porosity), 1.5 * float(diam.max()))
    z_insert = max(3.0 * z_dense, 2.5 * float(diam.max()))
    pos, rad, mat = random_bed(cfg, diam, mat, z_insert, rng)
    prep_cfg = with_overrides(cfg, {"numerics.timestep_fraction": 0.2,
                                    "numerics.rebuild_check_interval": 1})
    sim = Simulation(prep_cfg, capacity=len(rad))
    try:
        sim.add_particles(pos, rad, mat)
        sim.set_top_plate(z=z_insert + 0.5e-6)
        compress(sim, z_dense, prep_speed,
                 progress=_progress_printer("pre-compaction") if verbose else None)
        s = sim.state()
        return s["position"], s["radius"], s["material"], s["velocity"], sim.z_top
    finally:
        sim.destroy()


def main(argv: list[str] | None = None) -> int:
    """Run the demo compaction and write CSV, PNG and JSON into ``--out``."""
    ap = argparse.ArgumentParser(prog="python -m calendaring.demo", description=__doc__)
    ap.add_argument("--out", default="out/demo", help="output folder")
    ap.add_argument("--n-am", type=int, default=200, help="number of AM spheres")
    ap.add_argument("--n-cb", type=int, default=500, help="number of CB spheres")
    ap.add_argument("--cell", type=float, default=50e-6, help="periodic cell edge [m]")
    ap.add_argument("--porosity", type=float, default=0.5, help="porosity of the dense start")
    ap.add_argument("--strain", type=float, default=0.15, help="plate travel / start thickness")
    ap.add_argument("--speed", type=float, default=0.5, help="plate speed [m/s]")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from calendaring.simulation import Simulation

    cfg = with_overrides(SimConfig(), {"domain.cell_x": args.cell, "domain.cell_y": args.cell,
                                       "numerics.seed": args.seed})
    print(f"inserting {args.n_am} AM + {args.n_cb} CB spheres in a {to_um(args.cell):.0f} um cell")
    pos, rad, mat, vel, z_top = prepare_dense_bed(cfg, args.n_am, args.n_cb, args.porosity,
                                                  args.seed)
    stroke = args.strain * z_top
    sim = Simulation(cfg, capacity=len(rad))
    try:
        sim.add_particles(pos, rad, mat, velocity=vel)
        sim.set_top_plate(z=z_top)
        print(f"compaction at dt = {sim.compute_timestep():.3e} s (4 % Rayleigh), "
              f"plate speed {args.speed} m/s, stroke {to_um(stroke):.1f} um")
        rec = compress(sim, z_top - stroke, args.speed,
                       progress=_progress_printer("compaction"))
        energy = sim.energy()
    finally:
        sim.destroy()
    tmp = out / "pressure.csv.tmp"
    np.savetxt(tmp, np.column_stack([rec["travel"], rec["top_pressure"], rec["bottom_pressure"]]),
               delimiter=",", header="plate_travel_m,top_pressure_Pa,bottom_pressure_Pa",
               comments="")
    tmp.replace(out / "pressure.csv")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.6), dpi=120)
    ax.plot(to_um(rec["travel"]), to_mpa(rec["top_pressure"]), label="top plate")
    ax.plot(to_um(rec["travel"]), to_mpa(rec["bottom_pressure"]), "--", label="bottom plate")
    ax.set_xlabel("plate travel [um]")
    ax.set_ylabel("pressure [MPa]")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "pressure.png.tmp.png")
    plt.close(fig)
    (out / "pressure.png.tmp.png").replace(out / "pressure.png")
    summary = {"n_am": args.n_am, "n_cb": args.n_cb, "steps": rec["steps"],
               "wall_s": rec["wall"], "steps_per_s": rec["steps"] / rec["wall"],
               "final_top_pressure_Pa": float(rec["top_pressure"][-1]),
               "energy_J": {k: float(v) for k, v in energy.items()}}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"final top-plate pressure {to_mpa(rec['top_pressure'][-1]):.3f} MPa after "
          f"{to_um(stroke):.1f} um; {summary['steps_per_s']:.0f} steps/s")
    for name in ("pressure.csv", "pressure.png", "summary.json"):
        print(f"wrote {out / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

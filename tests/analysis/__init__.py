"""Tests of the analysis package. ``write_small_run`` writes a tiny run file through the
project's own writer (``calendaring.process.runfile.write_run``), so analysis code can be tested
through ``read_run`` without running the DEM engine."""

from pathlib import Path

import numpy as np


def write_small_run(path: str | Path, seed: int = 0) -> Path:
    """A run file of the ``tiny`` preset (25 x 25 um cell) with two snapshots of 40 random
    spheres (30 AM, 10 CB) between plates 25 and 20 um apart, each with a few bonds."""
    from calendaring.core.config import load_preset
    from calendaring.process.runfile import BONDS, BREAKAGE, FRAGMENTS, SERIES_UNITS, write_run

    cfg = load_preset("tiny")
    rng = np.random.default_rng(seed)
    n = 40
    radius = np.concatenate([rng.uniform(2.5e-6, 4.0e-6, 30), np.full(10, 1.5e-6)])
    material = np.concatenate([np.zeros(30, np.int32), np.ones(10, np.int32)])
    ids = np.arange(n, dtype=np.int64)
    snapshots = []
    for k, gap in enumerate((25e-6, 20e-6)):
        pos = rng.uniform([0, 0, 0], [cfg.domain.cell_x, cfg.domain.cell_y, gap], (n, 3))
        a = rng.integers(0, n, 12)
        b = (a + 1 + rng.integers(0, n - 1, 12)) % n
        zeros = np.zeros(n)
        snapshots.append({
            "data": {"position": pos, "radius": radius, "material": material, "id": ids,
                     "velocity": np.zeros((n, 3)), "normal_force": zeros,
                     "n_contacts": np.zeros(n, np.int64), "parent_id": -np.ones(n, np.int64),
                     "fracture_energy": zeros, "peak_load": zeros},
            "attrs": {"depth": 25e-6 - gap, "step": k, "time": 0.0, "z_top": gap,
                      "z_bottom": 0.0, "top_pressure": 0.0, "label": str(k)},
            "bonds": {"id_a": a, "id_b": b, "state": np.arange(12) % 4,
                      "normal_force": np.zeros(12), "radius": np.full(12, 1e-7)}})
    assert set(BONDS) == {"id_a", "id_b", "state", "normal_force", "radius"}
    empty = np.zeros(0)
    breakage = {k: empty for k in BREAKAGE}
    breakage["fragments"] = {k: empty for k in FRAGMENTS}
    return write_run(path, {
        "config": cfg, "preset": "tiny", "seed": seed, "info": {"synthetic": True},
        "breakage_model": "tavares_ufrj", "breakage": breakage,
        "pressure": {k: empty for k in ("step", "time", "depth", "value", "bottom")},
        "unloading": {k: empty for k in ("depth", "value", "bottom")},
        "series": {k: empty for k in SERIES_UNITS}, "energy": {},
        "snapshots": snapshots})

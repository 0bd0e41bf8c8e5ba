"""Fixtures for the inverse tests: one thread for torch, analytic stand-ins, fake run files."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from calendaring.process.runfile import BREAKAGE, FRAGMENTS, SERIES_UNITS, write_run


@pytest.fixture(autouse=True, scope="session")
def _one_thread():
    torch.set_num_threads(1)


def write_fake_run(path, depth, pressure, loads=(), diameters=(), preset="tiny", seed=0,
                   cfg=None, info=None):
    """A schema-valid run file with the given top-plate trace and breakage events (no DEM),
    with the configuration ``cfg`` (default: the preset's)."""
    from calendaring.core.config import load_preset

    cfg = cfg if cfg is not None else load_preset(preset)
    n = len(depth)
    k = len(loads)
    brk = {name: np.zeros(k) for name in BREAKAGE}
    brk["peak_load"] = np.asarray(loads, float)
    brk["diameter"] = np.asarray(diameters, float)
    brk["fragments"] = {name: np.zeros(0) for name in FRAGMENTS}
    series = {name: np.zeros(3) for name in SERIES_UNITS}
    return write_run(path, {
        "config": cfg, "preset": preset, "seed": seed, "info": info or {"fake": True},
        "breakage_model": "tavares_ufrj", "breakage": brk,
        "pressure": {"step": np.arange(n), "time": np.arange(n) * 1e-9,
                     "depth": np.asarray(depth, float), "value": np.asarray(pressure, float),
                     "bottom": np.asarray(pressure, float)},
        "unloading": {"depth": np.zeros(0), "value": np.zeros(0), "bottom": np.zeros(0)},
        "series": series, "energy": {"kinetic": np.zeros(3)}, "snapshots": []})

"""Neighbour search equals the O(N^2) brute force; capacity overflow grows the table."""

import numpy as np
import pytest

from calendaring.core.config import load_config_dict
from calendaring.engine.contacts import brute_force_pairs
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import random_gas


def _pairs(sim):
    """Candidate pairs as (smaller id, larger id): ids are the input indices, slots are
    not (the pool stores a bed along a space-filling curve)."""
    h = sim.table.history_arrays()
    pid = sim.pool.pid.to_numpy()
    return {tuple(sorted((int(pid[a]), int(pid[b]))))
            for a, b in zip(h["owner"], h["partner"], strict=True)}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grid_matches_brute_force_polydisperse_periodic(seed):
    # size ratio 5 (1 um .. 5 um radii); skin large so that many pairs cross the faces
    cfg = load_config_dict({"domain": {"cell_x": 40e-6, "cell_y": 32e-6, "height": 40e-6},
                            "numerics": {"skin": 1.0e-6}})
    sim = Simulation(cfg, capacity=400)
    try:
        pos, rad, _ = random_gas(sim, 300, 1e-6, 5e-6, seed, 0.0, 40e-6)
        # push a few particles onto the periodic faces
        pos[:10, 0] = np.linspace(0, 1e-7, 10)
        pos[10:20, 1] = 32e-6 - np.linspace(1e-9, 1e-7, 10)
        rng = np.random.default_rng(seed)
        sim.add_particles(pos, rad, rng.integers(0, 2, len(rad)))
        sim.rebuild()
        found = _pairs(sim)
        expected = brute_force_pairs(pos, rad, 40e-6, 32e-6, 1.0e-6)
        assert found == expected
        crossing = [(i, j) for i, j in expected if abs(pos[i, 0] - pos[j, 0]) > 20e-6
                    or abs(pos[i, 1] - pos[j, 1]) > 16e-6]
        assert crossing, "the test set must contain pairs across the periodic faces"
    finally:
        sim.destroy()


def test_small_periodic_cell_visits_each_pair_once():
    # fewer than 3 cells along x and y: every cell is visited once instead of 3 neighbours
    cfg = load_config_dict({"domain": {"cell_x": 22e-6, "cell_y": 22e-6, "height": 30e-6},
                            "numerics": {"skin": 0.5e-6}})
    sim = Simulation(cfg, capacity=100)
    try:
        pos, rad, _ = random_gas(sim, 40, 1e-6, 5e-6, 5, 0.0, 30e-6)
        sim.add_particles(pos, rad, np.zeros(len(rad), int))
        sim.rebuild()
        assert sim.grid.nx < 3
        h = sim.table.history_arrays()
        assert len(h["owner"]) == len(_pairs(sim))  # no duplicates
        assert _pairs(sim) == brute_force_pairs(pos, rad, 22e-6, 22e-6, 0.5e-6)
    finally:
        sim.destroy()


def test_pair_capacity_overflow_grows_table_and_keeps_every_pair():
    cfg = load_config_dict({"domain": {"cell_x": 40e-6, "cell_y": 40e-6, "height": 40e-6},
                            "numerics": {"skin": 2.0e-6, "pairs_per_particle": 1}})
    sim = Simulation(cfg, capacity=300)
    try:
        pos, rad, _ = random_gas(sim, 250, 1e-6, 3e-6, 3, 0.0, 40e-6)
        sim.add_particles(pos, rad, np.zeros(len(rad), int))
        sim.rebuild()
        expected = brute_force_pairs(pos, rad, 40e-6, 40e-6, 2.0e-6)
        assert len(expected) > 300  # more than the initial capacity
        assert sim.table.capacity >= len(expected)
        assert _pairs(sim) == expected
    finally:
        sim.destroy()


def test_owner_with_more_candidates_than_the_scratch_is_searched_again():
    """The rebuild's counting pass keeps up to CANDIDATE_SCRATCH partners per owner for the
    filling pass; an owner with more (a large sphere in slot 0 ringed by small ones) is
    searched again. Both paths give the brute-force pairs, once each."""
    from calendaring.engine.contacts import CANDIDATE_SCRATCH

    cfg = load_config_dict({"domain": {"cell_x": 40e-6, "cell_y": 40e-6, "height": 40e-6},
                            "numerics": {"skin": 0.5e-6}})
    sim = Simulation(cfg, capacity=200)
    try:
        rng = np.random.default_rng(4)
        centre, big, small = np.array([20e-6, 20e-6, 20e-6]), 8e-6, 1e-6
        u = rng.normal(size=(3 * CANDIDATE_SCRATCH, 3))
        u /= np.linalg.norm(u, axis=1)[:, None]
        shell = centre + (big + small + 0.2e-6) * u  # within the skin of the big sphere
        keep = [0]
        for k in range(1, len(shell)):  # small spheres apart from each other
            if np.min(np.linalg.norm(shell[keep] - shell[k], axis=1)) > 2.2 * small:
                keep.append(k)
        pos = np.vstack([centre, shell[keep]])
        rad = np.array([big] + [small] * len(keep))
        sim.add_particles(pos, rad, np.zeros(len(rad), int))  # input order: big in slot 0
        sim.rebuild()
        h = sim.table.history_arrays()
        assert int(np.sum(h["owner"] == 0)) == len(keep) > CANDIDATE_SCRATCH
        assert len(h["owner"]) == len(_pairs(sim))  # no duplicates
        assert _pairs(sim) == brute_force_pairs(pos, rad, 40e-6, 40e-6, 0.5e-6)
        assert np.any(h["owner"] > 0)  # the copied path too: small-small pairs
    finally:
        sim.destroy()


def test_cell_smaller_than_two_cutoffs_is_rejected():
    from calendaring.core.errors import ConfigError
    cfg = load_config_dict({"domain": {"cell_x": 12e-6, "cell_y": 40e-6, "height": 40e-6}})
    sim = Simulation(cfg, capacity=10)
    try:
        sim.add_particles([[5e-6, 5e-6, 10e-6]], [4e-6], [0])
        with pytest.raises(ConfigError, match="cell_x"):
            sim.rebuild()
    finally:
        sim.destroy()


@pytest.mark.parametrize("n", [0, 1, 255, 256, 257, 1000])
def test_blocked_exclusive_scan_equals_cumsum(n):
    import taichi as ti

    from calendaring.engine.neighbours import exclusive_scan, scan_blocks

    cap = 1024
    fb = ti.FieldsBuilder()
    count, start, block, total = (ti.field(ti.i32) for _ in range(4))
    fb.dense(ti.i, cap).place(count, start)
    fb.dense(ti.i, scan_blocks(cap)).place(block)
    fb.place(total)
    tree = fb.finalize()

    @ti.kernel
    def scan(m: ti.i32):
        exclusive_scan(count, start, total, block, m)

    try:
        values = np.random.default_rng(n).integers(0, 9, cap).astype(np.int32)
        count.from_numpy(values)
        start.fill(-7)
        scan(n)
        expected = np.concatenate([[0], np.cumsum(values[:n])])
        np.testing.assert_array_equal(start.to_numpy()[:n], expected[:n])
        assert total[None] == expected[n]
        assert np.all(start.to_numpy()[n:] == -7)  # nothing written past n
    finally:
        tree.destroy()

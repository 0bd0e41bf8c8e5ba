"""Particles stored along a space-filling curve: ids, outputs and physics are unchanged."""

import numpy as np
import pytest

from calendaring.core.errors import ConfigError
from calendaring.engine.contacts import brute_force_pairs
from calendaring.engine.neighbours import space_filling_order
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import frictionless_pair, jostled_lattice, random_gas


def test_space_filling_order_halves_and_quarters_are_slabs_across_x_then_y():
    # an 8 x 8 x 4 lattice in a 40 um periodic cell: with x the most significant bit the
    # first half of the ranks is exactly the x < L/2 half of the box, the first quarter the
    # x < L/2, y < L/2 quarter
    lx = 40e-6
    g = (np.arange(8) + 0.5) * lx / 8
    x, y, z = np.meshgrid(g, g, np.arange(4) * 1e-6, indexing="ij")
    pos = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    rng = np.random.default_rng(3)
    pos = pos[rng.permutation(len(pos))]
    order = space_filling_order(pos, lx, lx)
    assert np.array_equal(np.sort(order), np.arange(len(pos)))
    ranked = pos[order]
    n = len(pos)
    assert np.all(ranked[: n // 2, 0] < lx / 2) and np.all(ranked[n // 2:, 0] > lx / 2)
    q = ranked[: n // 4]
    assert np.all(q[:, 0] < lx / 2) and np.all(q[:, 1] < lx / 2)
    # positions outside [0, L) are wrapped first
    shifted = pos.copy()
    shifted[:, 0] += lx
    shifted[:, 1] -= 3 * lx
    assert np.array_equal(space_filling_order(shifted, lx, lx), order)


def test_space_order_puts_neighbours_in_nearby_slots():
    cfg = frictionless_pair(restitution=0.5)
    sim = Simulation(cfg, capacity=3000)
    try:
        pos, rad, _ = random_gas(sim, 1500, 1.0e-6, 1.6e-6, 11, 0.0, 60e-6)
        order = space_filling_order(pos, cfg.domain.cell_x, cfg.domain.cell_y)
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order))
        pairs = np.array(sorted(brute_force_pairs(pos, rad, cfg.domain.cell_x,
                                                  cfg.domain.cell_y, 1e-6)))
        gap_input = np.median(np.abs(pairs[:, 0] - pairs[:, 1]))
        gap_space = np.median(np.abs(rank[pairs[:, 0]] - rank[pairs[:, 1]]))
        # input order is random: a typical pair is ~n/3 slots apart; along the curve a
        # particle's neighbours are mostly within a few dozen slots
        assert gap_input > 300
        assert gap_space < gap_input / 10
    finally:
        sim.destroy()


@pytest.mark.parametrize("order", ["space", "input"])
def test_ids_follow_the_input_and_state_lists_particles_by_id(order):
    cfg = frictionless_pair(restitution=0.5)
    sim = Simulation(cfg, capacity=1000)
    try:
        pos, rad, vel = random_gas(sim, 400, 1.0e-6, 1.6e-6, 5, 0.0, 60e-6, speed=0.1)
        mat = np.arange(len(rad)) % 2
        ids = sim.add_particles(pos, rad, mat, velocity=vel, order=order)
        assert np.array_equal(ids, np.arange(len(rad)))
        slots = sim.pool.to_numpy(("pid", "position"))
        assert np.array_equal(slots["position"][np.argsort(slots["pid"])], pos)
        if order == "space":  # the pool really is permuted
            assert not np.array_equal(slots["pid"], np.arange(len(rad)))
        else:
            assert np.array_equal(slots["pid"], np.arange(len(rad)))
        s = sim.state()
        assert np.array_equal(s["id"], ids)
        assert np.array_equal(s["position"], pos)
        assert np.array_equal(s["radius"], rad)
        assert np.array_equal(s["material"], mat)
        sim.pool.remove(ids[:10])
        assert np.array_equal(sim.state()["id"], ids[10:])
    finally:
        sim.destroy()


def test_unknown_order_is_refused():
    sim = Simulation(frictionless_pair(), capacity=8)
    try:
        with pytest.raises(ConfigError, match="order"):
            sim.add_particles([[1e-5, 1e-5, 1e-5]], [1e-6], [0], order="random")
        with pytest.raises(ValueError, match="permutation"):
            sim.pool.add([[1e-5, 1e-5, 1e-5], [2e-5, 1e-5, 1e-5]], [1e-6, 1e-6], [0, 0],
                         [1e-15, 1e-15], order=[0, 0])
        with pytest.raises(ValueError, match="finite"):
            sim.add_particles([[1e-5, np.nan, 1e-5]], [1e-6], [0], order="space")
        assert sim.pool.slots_used == 0  # nothing half-written
    finally:
        sim.destroy()


def test_slot_order_does_not_change_the_physics():
    # the same jostled bed stored in input order and along the curve, squeezed by the top
    # plate: a step sums a particle's contacts in slot order, so the runs differ by
    # rounding only
    out = []
    for order in ("input", "space"):
        cfg = frictionless_pair(restitution=0.7, friction=0.4, rolling=0.05)
        sim = Simulation(cfg, capacity=1100)
        try:
            pos, rad, vel, top = jostled_lattice(16, 4, 4)  # ~2,500 contacts at once
            sim.add_particles(pos, rad, np.arange(len(rad)) % 2, velocity=vel, order=order)
            sim.set_top_plate(z=top, velocity=-2.0)
            sim.run(1500)
            s = sim.state()
            out.append((s["position"], s["velocity"], sim.plate_forces()[1][2],
                        sim.contact_stats()[0]))
        finally:
            sim.destroy()
    (pa, va, fa, na), (pb, vb, fb, nb) = out
    assert na == nb and na > 2000  # contacts were exercised, the same ones
    assert fa > 0.0
    np.testing.assert_allclose(pb, pa, rtol=0, atol=1e-15)  # positions [m], ~1e-5 m
    np.testing.assert_allclose(vb, va, rtol=0, atol=1e-9 * np.abs(va).max())
    assert fb == pytest.approx(fa, rel=1e-9)

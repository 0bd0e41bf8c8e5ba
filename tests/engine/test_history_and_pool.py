"""Contact history survives rebuilds; the pool never reuses ids and never drops particles."""

import numpy as np
import pytest
import taichi as ti

from calendaring.core.errors import SimulationError
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import frictionless_pair


def _spring_of(sim, id_a, id_b):
    h = sim.table.history_arrays()
    pid = sim.pool.pid.to_numpy()
    for c in range(len(h["owner"])):
        ids = {int(pid[h["owner"][c]]), int(h["partner_id"][c])}
        if ids == {id_a, id_b}:
            return h["spring"][c], h["delta_max"][c]
    raise AssertionError("pair not in the table")


def _sheared_pair():
    sim = Simulation(frictionless_pair(restitution=0.5, plasticity=0.8, friction=1.0),
                     capacity=64)
    r = 3.87e-6
    # pressed together along x at 1 m/s (contact lasts ~600 steps) and sheared along z
    ids = sim.add_particles([[20e-6, 30e-6, 30e-6], [20e-6 + 2 * r - 1e-9, 30e-6, 30e-6]],
                            [r, r], [0, 0], velocity=[[0.5, 0, 0.1], [-0.5, 0, -0.1]])
    return sim, ids


def test_sheared_pair_keeps_its_tangential_spring_across_rebuilds():
    sim, ids = _sheared_pair()
    try:
        sim.run(100)
        spring0, dmax0 = _spring_of(sim, *ids)
        assert np.linalg.norm(spring0) > 0 and dmax0 > 0
        # new particles shift every segment of the CSR table
        far = sim.add_particles([[50e-6, 5e-6, 10e-6], [5e-6, 50e-6, 50e-6]], [2e-6, 2e-6], [1, 1])
        assert len(far) == 2
        sim.prime()  # new particles -> new forces and a rebuilt list
        spring1, dmax1 = _spring_of(sim, *ids)
        np.testing.assert_allclose(spring1, spring0, rtol=1e-12)
        assert dmax1 == dmax0
        sim.rebuild()
        spring2, _ = _spring_of(sim, *ids)
        np.testing.assert_allclose(spring2, spring0, rtol=1e-12)
    finally:
        sim.destroy()


def test_run_with_extra_rebuilds_equals_run_without():
    a, _ = _sheared_pair()
    b, _ = _sheared_pair()
    try:
        a.run(100)
        b.run(100)
        for _ in range(5):
            a.rebuild()  # b never rebuilds (displacements are far below the skin)
            a.run(20)
            b.run(20)
        sa, sb = a.state(), b.state()
        assert a.n_rebuilds == b.n_rebuilds + 5
        assert np.linalg.norm(_spring_of(b, *sb["id"][:2])[0]) > 0
        np.testing.assert_allclose(sa["force"], sb["force"], rtol=1e-12, atol=0)
        np.testing.assert_allclose(sa["angular_velocity"], sb["angular_velocity"], rtol=1e-12)
    finally:
        a.destroy()
        b.destroy()


def test_pair_table_growth_keeps_every_contact_history():
    # A rebuild that finds the table too small grows it. The pairs' history (here a
    # sheared pair's spring and delta_max) must come along, looked up through the segments
    # saved before the failed count overwrote them: new candidates of lower slots shift
    # the pair's segment.
    sim = Simulation(frictionless_pair(restitution=0.5, plasticity=0.8, friction=1.0,
                                       pairs_per_particle=1), capacity=128)
    try:
        g = np.arange(30)  # a 5 x 6 lattice of CB spheres 4.1 um apart: no candidates
        lattice = np.column_stack([4e-6 + 4.1e-6 * (g % 5), 4e-6 + 4.1e-6 * (g // 5),
                                   np.full(30, 50e-6)])
        sim.add_particles(lattice, np.full(30, 0.9e-6), [1] * 30)
        r = 3.87e-6
        ids = sim.add_particles([[40e-6, 30e-6, 20e-6], [40e-6 + 2 * r - 1e-9, 30e-6, 20e-6]],
                                [r, r], [0, 0], velocity=[[0.5, 0, 0.1], [-0.5, 0, -0.1]])
        sim.run(100)
        spring0, dmax0 = _spring_of(sim, *ids)
        assert np.linalg.norm(spring0) > 0 and dmax0 > 0
        cap0 = sim.table.capacity
        # a sphere between each two lattice neighbours: 98 new candidate pairs
        mid = [(lattice[k] + lattice[k + 1]) / 2 for k in range(30) if k % 5 < 4]
        mid += [(lattice[k] + lattice[k + 5]) / 2 for k in range(25)]
        sim.add_particles(np.array(mid), np.full(len(mid), 0.9e-6), [1] * len(mid))
        sim.rebuild()
        assert sim.table.capacity > cap0  # the table grew in this rebuild
        spring1, dmax1 = _spring_of(sim, *ids)
        np.testing.assert_allclose(spring1, spring0, rtol=1e-12)
        assert dmax1 == dmax0
    finally:
        sim.destroy()


@ti.kernel
def _spawn(pool: ti.template(), n: ti.i32, radius: ti.f64):
    for _k in range(n):
        slot, _new_id = pool.allocate_slot()
        if slot >= 0:
            pool.alive[slot] = 1
            pool.radius[slot] = radius
            pool.parent_id[slot] = -2


def test_device_insertion_gives_unique_fresh_ids_and_flags_a_full_pool():
    cfg = frictionless_pair()
    sim = Simulation(cfg, capacity=40)
    try:
        first = sim.add_particles(np.full((5, 3), 20e-6) + np.arange(5)[:, None] * 8e-6,
                                  np.full(5, 3e-6), np.zeros(5, int))
        sim.pool.remove(first[:2])
        _spawn(sim.pool, 20, 1e-6)
        a = sim.pool.to_numpy(("pid", "alive", "parent_id"))
        assert sim.pool.slots_used == 25
        spawned = a["pid"][5:]
        assert len(set(spawned.tolist())) == 20
        assert set(spawned.tolist()).isdisjoint(first.tolist())  # removed ids are not reused
        assert np.all(a["parent_id"][5:] == -2)
        assert sim.pool.n_alive() == 23
        sim.pool.check_overflow()  # still fits
        _spawn(sim.pool, 30, 1e-6)  # 15 fit, 15 do not
        assert sim.pool.slots_used == 40
        with pytest.raises(SimulationError, match="pool full"):
            sim.pool.check_overflow()
        with pytest.raises(SimulationError, match="pool full"):
            sim.add_particles([[1e-6, 1e-6, 1e-6]], [1e-6], [0])
        ids = sim.pool.pid.to_numpy()[:40]
        assert len(set(ids.tolist())) == 40
    finally:
        sim.destroy()


def test_host_removal_of_unknown_id_is_an_error():
    sim = Simulation(frictionless_pair(), capacity=4)
    try:
        sim.add_particles([[20e-6, 20e-6, 20e-6]], [3e-6], [0])
        with pytest.raises(KeyError, match="99"):
            sim.pool.remove([99])
    finally:
        sim.destroy()

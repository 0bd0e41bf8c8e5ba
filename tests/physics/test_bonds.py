"""Potyondy-Cundall bonds (spec section 4; analytic checks T7 and T18).

The kinematic tests drive two bonded spheres with prescribed velocities and call the bond
kernel alone, so every increment is known exactly: F_n = -S_n A du, F_t = -S_t A ds,
M_t = -S_n I theta, M_n = -S_t J phi, failure at the stretch, slip, bend or twist where the
stress reaches the strength.
"""

import math

import numpy as np
import pytest

from calendaring.core.config import SimConfig, with_overrides
from calendaring.engine.bonds import FAILED_NORMAL, FAILED_SHEAR, INTACT, find_bond_pairs
from calendaring.engine.simulation import Simulation

S = 3.5e13  # N/m^3
SIGMA = 5e7  # Pa
R = 1.5e-6  # CB radius [m]
DT = 1e-9


def _cfg(**over):
    base = {"domain.cell_x": 50e-6, "domain.cell_y": 50e-6, "domain.height": 50e-6,
            "domain.gravity": 0.0}
    base.update(over)
    return with_overrides(SimConfig(), base)


def _pair(cfg, distance=3.6e-6, radii=(R, R), mats=(1, 1)):
    sim = Simulation(cfg, capacity=2)
    pos = np.array([[20e-6, 20e-6, 25e-6], [20e-6 + distance, 20e-6, 25e-6]])
    sim.add_particles(pos, np.array(radii), np.array(mats))
    sim.prime()
    return sim


def _drive(sim, v=None, w=None, steps=1, move=True):
    """Advance the pair kinematically with the bond kernel only; returns the step of failure."""
    v = np.zeros((2, 3)) if v is None else v
    w = np.zeros((2, 3)) if w is None else w
    pool, bonds = sim.pool, sim.bonds
    pos = pool.position.to_numpy()
    for k in range(steps):
        if move:
            pos = pos + v * DT
        pool.position.from_numpy(pos)
        pool.velocity.from_numpy(np.asarray(v, float))
        pool.angular_velocity.from_numpy(np.asarray(w, float))
        bonds.update(pool, DT, 50e-6, 50e-6, k + 1)
        if int(bonds.state[0]) != INTACT:
            return k + 1
    return None


def test_axial_stretch_force_and_tension_failure():
    sim = _pair(_cfg())
    try:
        assert sim.create_bonds() == 1
        area = math.pi * R**2
        v = np.array([[-0.5, 0, 0], [0.5, 0, 0]])  # stretch rate 1 m/s
        assert _drive(sim, v, steps=500) is None
        du = 500 * 1.0 * DT
        assert float(sim.bonds.f_n[0]) == pytest.approx(-S * area * du, rel=1e-12)
        broke = _drive(sim, v, steps=2000)
        du_star = SIGMA / S  # 1.4286e-6 m, independent of R_b
        assert du_star == pytest.approx(1.4286e-6, rel=1e-4)
        assert (500 + broke) == math.ceil(du_star / DT - 1e-9)
        assert int(sim.bonds.state[0]) == FAILED_NORMAL
    finally:
        sim.destroy()


@pytest.mark.parametrize("criterion, breaks", [("tension", False), ("abs", True)])
def test_compression_breaks_only_in_abs_mode(criterion, breaks):
    sim = _pair(_cfg(**{"bonds.normal_criterion": criterion}), distance=4.4e-6)
    try:
        sim.create_bonds()
        v = np.array([[0.5, 0, 0], [-0.5, 0, 0]])
        n_star = math.ceil(SIGMA / S / DT - 1e-9)
        broke = _drive(sim, v, steps=n_star + 5)
        assert (broke is not None) == breaks
        if breaks:
            assert broke == n_star
            assert int(sim.bonds.state[0]) == FAILED_NORMAL
        else:
            assert float(sim.bonds.f_n[0]) > 0  # compression positive, still intact
    finally:
        sim.destroy()


def test_shear_force_and_failure():
    """Co-rotating spheres with fixed centres: pure tangential slip at the bond point."""
    sim = _pair(_cfg())
    try:
        sim.create_bonds()
        dist = 3.6e-6
        omega = 1.0 / dist  # |v_t| = omega x distance = 1 m/s
        w = np.array([[0, 0, omega], [0, 0, omega]])
        assert _drive(sim, w=w, steps=300, move=False) is None
        ft = sim.bonds.f_t.to_numpy()[0]
        area = math.pi * R**2
        assert np.linalg.norm(ft) == pytest.approx(S * area * 300 * DT, rel=1e-9)
        assert abs(float(sim.bonds.f_n[0])) < 1e-20
        broke = _drive(sim, w=w, steps=3000, move=False)
        assert 300 + broke == math.ceil(SIGMA / S / DT - 1e-9)  # ds* = tau_c / S_t
        assert int(sim.bonds.state[0]) == FAILED_SHEAR
    finally:
        sim.destroy()


@pytest.mark.parametrize("axis, state", [(2, FAILED_NORMAL), (0, FAILED_SHEAR)])
def test_bending_and_torsion_failure_angles(axis, state):
    """Counter-rotation about z bends (theta* = sigma_c/(S_n R_b)); about the bond axis x it
    twists (phi* = tau_c/(S_t R_b)). 0.952 rad for R_b = 1.5 um."""
    sim = _pair(_cfg())
    try:
        sim.create_bonds()
        omega = 0.5e8  # relative rotation rate 1e8 rad/s -> 0.1 rad per step
        w = np.zeros((2, 3))
        w[0, axis], w[1, axis] = omega, -omega
        theta_star = SIGMA / (S * R)
        assert theta_star == pytest.approx(0.952, abs=1e-3)
        broke = _drive(sim, w=w, steps=100, move=False)
        assert broke == math.ceil(theta_star / (2 * omega * DT) - 1e-9)
        assert int(sim.bonds.state[0]) == state
    finally:
        sim.destroy()


def test_bond_pairs_rules_match_brute_force():
    rng = np.random.default_rng(4)
    n = 300
    lx = ly = 30e-6
    pos = rng.uniform([0, 0, 0], [lx, ly, 20e-6], size=(n, 3))
    mat = (rng.uniform(size=n) < 0.7).astype(np.int32)  # 1 = CB
    rad = np.where(mat == 1, 1.5e-6, rng.uniform(2.5e-6, 5e-6, size=n))
    got = {tuple(p) for p in find_bond_pairs(pos, rad, mat, lx, ly, 1.5, [1]).tolist()}
    want = set()
    for a in range(n):
        for b in range(a + 1, n):
            d = pos[b] - pos[a]
            d[0] -= lx * round(d[0] / lx)
            d[1] -= ly * round(d[1] / ly)
            if (mat[a] == 1 or mat[b] == 1) and np.linalg.norm(d) <= 1.5 * (rad[a] + rad[b]):
                want.add((a, b))
    assert got == want
    assert len(want) > 100
    assert all(mat[a] == 1 or mat[b] == 1 for a, b in got)  # never AM-AM


def test_no_bond_beyond_reach_and_created_once():
    sim = _pair(_cfg(), distance=1.5 * 2 * R * 1.0001)
    try:
        assert sim.create_bonds() == 0
        with pytest.raises(Exception, match="created once"):
            sim.create_bonds()
    finally:
        sim.destroy()


def test_bonded_pair_conserves_energy():
    """A bonded CB pair (not touching) vibrating and spinning under full dynamics: the
    ledger total (kinetic + rotational + bond elastic) stays constant."""
    sim = _pair(_cfg(), distance=4.0e-6)
    try:
        sim.create_bonds()
        sim.pool.velocity.from_numpy(np.array([[0.02, 0.01, 0.0], [-0.02, 0.0, 0.005]]))
        sim.pool.angular_velocity.from_numpy(np.array([[1e3, 2e3, 0.0], [0.0, -1e3, 5e3]]))
        sim._primed = False
        sim.prime()
        e0 = sim.energy()
        scale = e0["kinetic"] + e0["rotational"]
        totals, stored = [], []
        for _ in range(20):
            sim.run(200)
            e = sim.energy()
            totals.append(e["total"])
            stored.append(e["bond_elastic"])
            assert int(sim.bonds.state[0]) == INTACT
        assert max(abs(t - e0["total"]) for t in totals) < 2e-3 * scale
        # the bond really exchanges energy with the motion (not a free flight)
        assert max(stored) > 0.05 * scale
    finally:
        sim.destroy()

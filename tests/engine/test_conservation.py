"""Conservation laws: momentum to round-off, energy with e = 1 and no friction, the ledger,
and a column at rest whose weight is carried by the bottom plate."""

import math

import numpy as np
import pytest

from calendaring.core.config import load_config_dict
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import frictionless_pair, random_gas


def _gas_config(**pair):
    base = {"plasticity_ratio": 0.8, "surface_energy": 20.0, "restitution": 0.25,
            "friction": 0.3, "rolling_friction": 0.05}
    base.update(pair)
    return load_config_dict({
        "domain": {"gravity": 0.0, "cell_x": 30e-6, "cell_y": 30e-6, "height": 200e-6},
        "contact": {"pairs": {"AM-AM": base, "AM-CB": base, "CB-CB": base}},
        "numerics": {"timestep_fraction": 0.02, "rebuild_check_interval": 5},
    })


def test_linear_momentum_is_conserved_to_round_off_with_full_contact_model():
    sim = Simulation(_gas_config(), capacity=200)
    try:
        pos, rad, vel = random_gas(sim, 120, 1.5e-6, 4e-6, 11, 60e-6, 140e-6, speed=0.5)
        mats = (rad < 2.5e-6).astype(int)  # CB-sized spheres are CB
        sim.add_particles(pos, rad, mats, velocity=vel,
                          angular_velocity=np.random.default_rng(1).normal(size=(120, 3)) * 1e5)
        s0 = sim.state()
        p0 = (s0["mass"][:, None] * s0["velocity"]).sum(0)
        scale = (s0["mass"] * np.linalg.norm(s0["velocity"], axis=1)).sum()
        sim.run(3000)
        s1 = sim.state()
        assert s1["n_contacts"].sum() > 0 or sim.energy()["damping_normal"] > 0
        p1 = (s1["mass"][:, None] * s1["velocity"]).sum(0)
        np.testing.assert_allclose(p1, p0, atol=1e-12 * scale)
        assert sim.energy()["damping_normal"] > 0  # collisions really happened
    finally:
        sim.destroy()


def test_energy_conserved_elastic_frictionless_gas():
    sim = Simulation(_gas_config(plasticity_ratio=0.0, surface_energy=0.0, restitution=1.0,
                                 friction=0.0, rolling_friction=0.0), capacity=200)
    try:
        pos, rad, vel = random_gas(sim, 120, 1.5e-6, 4e-6, 12, 60e-6, 140e-6, speed=1.0)
        sim.add_particles(pos, rad, np.zeros(len(rad), int), velocity=vel)
        e0 = sim.energy()
        ledger = []
        for _ in range(6):
            sim.run(1000)
            ledger.append(sim.energy())
        kin0 = e0["kinetic"]
        n_coll = (sum(1 for e in ledger if e["elastic"] > 0)
                  + int(ledger[-1]["hysteretic_work"] != 0))
        assert n_coll > 0, "no collision happened; the test would be empty"
        for e in ledger:
            assert e["kinetic"] + e["elastic"] == pytest.approx(kin0, rel=2e-4)
            assert e["rotational"] == pytest.approx(0.0, abs=1e-12 * kin0)
    finally:
        sim.destroy()


def test_energy_ledger_closes_with_dissipation():
    # plastic, adhesive, damped and frictional collisions: every joule is accounted for
    sim = Simulation(_gas_config(), capacity=200)
    try:
        pos, rad, vel = random_gas(sim, 120, 1.5e-6, 4e-6, 13, 60e-6, 140e-6, speed=1.0)
        sim.add_particles(pos, rad, np.zeros(len(rad), int), velocity=vel)
        e0 = sim.energy()
        sim.run(6000)
        e1 = sim.energy()
        dissipated = (e1["damping_normal"] + e1["damping_tangential"] + e1["friction"]
                      + e1["rolling"] + e1["plastic"])
        assert dissipated > 0.05 * e0["total"]
        assert e1["kinetic"] < e0["kinetic"]
        assert e1["total"] == pytest.approx(e0["total"], rel=5e-3)
    finally:
        sim.destroy()


def test_column_at_rest_bottom_plate_carries_the_weight():
    # A 3-sphere column dropped from touching contact settles under gravity. The pair damping
    # uses the pair's reduced mass, so a stacked mode is less damped than a binary collision;
    # the force is averaged over the last oscillation periods and must also have settled.
    cfg = frictionless_pair(restitution=0.1, plasticity=0.8, friction=0.12, rolling=0.01,
                            fraction=0.1, gravity=9.81)
    sim = Simulation(cfg, capacity=16)
    try:
        radii = np.array([3.5e-6, 3.0e-6, 3.5e-6])
        z = np.cumsum(2 * radii) - radii  # touching, the bottom one on the plate
        n = len(radii)
        pos = np.column_stack([np.full(n, 30e-6), np.full(n, 30e-6), z])
        sim.add_particles(pos, radii, np.zeros(n, int))
        weight = (sim.state()["mass"] * 9.81).sum()
        forces = []
        for _ in range(150):
            sim.run(200)
            forces.append(-sim.plate_forces()[0][2])
        forces = np.array(forces)
        assert np.std(forces[:50]) > 10 * np.std(forces[-50:])  # it came to rest
        assert np.mean(forces[-50:]) == pytest.approx(weight, rel=1e-2)
        assert forces[-1] == pytest.approx(weight, rel=1e-2)
        assert sim.top_pressure() == 0.0
        assert sim.bottom_pressure() == pytest.approx(weight / sim.cell_area, rel=1e-2)
        assert math.isfinite(sim.energy()["total"])
    finally:
        sim.destroy()

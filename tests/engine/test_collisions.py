"""Binary collisions against analytic results (spec T2, Hertz force and contact duration)."""

import math

import numpy as np
import pytest

from calendaring.engine.contact_params import reduced_modulus
from calendaring.engine.simulation import Simulation
from tests.engine.helpers import frictionless_pair

R = 3.87e-6  # AM radius [m]


def _collide(cfg, v0, radius=R, block=5):
    """Head-on collision of two equal AM spheres; returns (e_out, contact steps, sim dt)."""
    sim = Simulation(cfg, capacity=4)
    try:
        gap = 1e-9
        sim.add_particles([[20e-6, 30e-6, 30e-6], [20e-6 + 2 * radius + gap, 30e-6, 30e-6]],
                          [radius, radius], [0, 0],
                          velocity=[[v0 / 2, 0, 0], [-v0 / 2, 0, 0]])
        touching = 0
        for _ in range(20000 // block):
            sim.run(block)
            x = sim.pool.position.to_numpy()[:2, 0]
            if x[1] - x[0] < 2 * radius:
                touching += block
            elif touching:
                break
        v = sim.state()["velocity"]
        return (v[1, 0] - v[0, 0]) / v0, touching, sim.dt
    finally:
        sim.destroy()


@pytest.mark.parametrize("e", [0.1, 0.25, 0.5, 0.9])
@pytest.mark.parametrize("v0", [0.01, 1.0])
def test_restitution_hertz_tangent_damping(e, v0):
    e_out, steps, _ = _collide(frictionless_pair(restitution=e), v0)
    assert steps >= 200
    assert e_out == pytest.approx(e, abs=1e-3)


@pytest.mark.parametrize("e", [0.1, 0.9])
def test_restitution_linear_eepa_paper_eq10(e):
    cfg = frictionless_pair(restitution=e, exponent=1.0, fraction=0.004)
    e_out, steps, _ = _collide(cfg, 1.0)
    assert steps >= 200
    assert e_out == pytest.approx(e, abs=1e-3)


def test_restitution_without_sqrt56_factor_is_wrong_as_documented():
    # spec T2: plugging k1 literally (no sqrt(5/6), no tangent stiffness) misses the target
    cfg = frictionless_pair(restitution=0.25)
    from calendaring.core.config import with_overrides
    cfg = with_overrides(cfg, {"contact.damping_mode": "literal_k1"})
    e_out, _, _ = _collide(cfg, 1.0)
    assert abs(e_out - 0.25) > 0.02


def test_hertz_contact_duration_and_peak_overlap():
    v0 = 0.5
    e_out, steps, dt = _collide(frictionless_pair(restitution=1.0), v0, block=2)
    assert e_out == pytest.approx(1.0, abs=1e-3)
    from calendaring.core.config import SimConfig
    am = SimConfig().materials["AM"]
    e_star = reduced_modulus(am, am)
    r_star = R / 2
    m = am.density * 4 / 3 * math.pi * R**3
    m_star = m / 2
    # Johnson (1985): delta_max = (15 m* v^2 / (16 E* sqrt(R*)))^(2/5), t_c = 2.9432 delta_max / v
    delta_max = (15 * m_star * v0**2 / (16 * e_star * math.sqrt(r_star))) ** 0.4
    t_c = 2.9432 * delta_max / v0
    assert steps * dt == pytest.approx(t_c, rel=0.01)  # steps counted in blocks of 2


def test_static_hertz_force_pair_and_plate():
    cfg = frictionless_pair(restitution=0.5)
    sim = Simulation(cfg, capacity=4)
    try:
        delta = 0.05e-6
        z_plate = 10e-6
        sim.add_particles([[20e-6, 30e-6, 30e-6], [20e-6 + 2 * R - delta, 30e-6, 30e-6],
                           [40e-6, 40e-6, z_plate + R - delta]], [R, R, R], [0, 0, 0])
        sim.z_bottom = z_plate
        sim.prime()
        s = sim.state()
        am = cfg.materials["AM"]
        e_star = reduced_modulus(am, am)
        f_pair = 4 / 3 * e_star * math.sqrt(R / 2) * delta**1.5
        np.testing.assert_allclose(s["force"][0], [-f_pair, 0, 0], rtol=1e-9, atol=1e-20)
        np.testing.assert_allclose(s["force"][1], [f_pair, 0, 0], rtol=1e-9, atol=1e-20)
        e_plate = reduced_modulus(am, cfg.plates.bottom)
        f_plate = 4 / 3 * e_plate * math.sqrt(R) * delta**1.5
        np.testing.assert_allclose(s["force"][2][2], f_plate, rtol=1e-9)
        fb, _ = sim.plate_forces()
        np.testing.assert_allclose(fb[2], -f_plate, rtol=1e-9)
    finally:
        sim.destroy()

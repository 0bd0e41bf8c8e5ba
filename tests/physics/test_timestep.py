"""Rayleigh time step (calendaring.engine.timestep) against spec 1.3 and check T6."""

import math

import numpy as np
import pytest

from calendaring.core.config import SimConfig
from calendaring.engine.timestep import critical_timestep, rayleigh_time

CFG = SimConfig()
AM = CFG.materials["AM"]
CB = CFG.materials["CB"]
MATERIALS = [CFG.materials[name] for name in CFG.material_names]  # index 0 = AM, 1 = CB
R_AM_MIN = 0.5 * 4.94e-6  # smallest (capped) AM radius [m]
R_CB = 0.5 * 3.0e-6  # CB radius [m]


def test_material_order_is_am_then_cb():
    assert CFG.material_names == ["AM", "CB"]


def test_rayleigh_time_am_smallest_particle():
    """T6: T_R(AM, d = 4.94 um) = 2.242e-9 s (4 figures)."""
    np.testing.assert_allclose(rayleigh_time(R_AM_MIN, AM), 2.242e-9, rtol=1e-3)
    # EDEM formula written out with G = E / (2 (1 + nu)) = 6.7536e10 Pa (spec 1.2)
    g = 168.30e9 / (2 * (1 + 0.246))
    np.testing.assert_allclose(AM.shear_modulus, 6.7536e10, rtol=1e-4)
    expected = math.pi * R_AM_MIN * math.sqrt(4740.0 / g) / (0.1631 * 0.246 + 0.8766)
    np.testing.assert_allclose(rayleigh_time(R_AM_MIN, AM), expected, rtol=1e-13)


def test_rayleigh_time_cb():
    """T6: T_R(CB, d = 3 um) = 1.477e-8 s (section 1.3 rounds it to 1.48e-8 s)."""
    t_cb = rayleigh_time(R_CB, CB)
    np.testing.assert_allclose(t_cb, 1.477e-8, rtol=1e-3)
    np.testing.assert_allclose(t_cb, 1.48e-8, rtol=5e-3)


def test_fragment_rayleigh_time():
    """Spec 1.3: a 2 um AM fragment has T_R = 9.08e-10 s and dt = 8.97e-11 s is 9.9 % of it."""
    t_frag = rayleigh_time(1.0e-6, AM)
    np.testing.assert_allclose(t_frag, 9.08e-10, rtol=1e-3)
    np.testing.assert_allclose(8.97e-11 / t_frag, 0.099, rtol=5e-3)


def test_critical_timestep_paper_fraction():
    """T6: dt = 0.04 T_R(smallest AM) = 8.970e-11 s; AM governs over CB."""
    radii = np.array([R_CB, 3.87e-6, R_AM_MIN, 5.3e-6, R_CB])
    mats = np.array([1, 0, 0, 0, 1])
    dt = critical_timestep(radii, mats, MATERIALS, fraction=0.04)
    np.testing.assert_allclose(dt, 8.970e-11, rtol=1e-3)
    np.testing.assert_allclose(dt, 0.04 * rayleigh_time(R_AM_MIN, AM), rtol=1e-14)
    # only CB present: the CB time governs
    dt_cb = critical_timestep(radii[mats == 1], mats[mats == 1], MATERIALS, fraction=0.04)
    np.testing.assert_allclose(dt_cb, 0.04 * 1.477e-8, rtol=1e-3)


@pytest.mark.parametrize("s", [1.0, 4.0, 100.0, 1.0e4])
def test_density_scaling_multiplies_by_sqrt_s(s):
    """rho -> s rho: T_R and dt scale by sqrt(s)."""
    np.testing.assert_allclose(rayleigh_time(R_AM_MIN, AM, density_scaling=s),
                               2.242e-9 * math.sqrt(s), rtol=1e-3)
    base = critical_timestep([R_AM_MIN], [0], MATERIALS, 0.04)
    scaled = critical_timestep([R_AM_MIN], [0], MATERIALS, 0.04, density_scaling=s)
    np.testing.assert_allclose(scaled / base, math.sqrt(s), rtol=1e-13)


def test_critical_timestep_includes_min_radius():
    """min_radius adds a future smallest particle (e.g. a 2 um fragment) to the minimum."""
    radii = np.array([R_AM_MIN, R_CB])
    mats = np.array([0, 1])
    dt = critical_timestep(radii, mats, MATERIALS, 0.04, min_radius={0: 1.0e-6})
    np.testing.assert_allclose(dt, 0.04 * 9.08e-10, rtol=1e-3)
    # a min_radius larger than the present particles does not change the minimum
    dt_big = critical_timestep(radii, mats, MATERIALS, 0.04, min_radius={0: 5.0e-6})
    np.testing.assert_allclose(dt_big, 8.970e-11, rtol=1e-3)
    # min_radius alone (no particles yet) is enough
    dt_only = critical_timestep([], [], MATERIALS, 0.04, min_radius={1: R_CB})
    np.testing.assert_allclose(dt_only, 0.04 * 1.477e-8, rtol=1e-3)


def test_critical_timestep_needs_a_candidate():
    with pytest.raises(ValueError):
        critical_timestep([], [], MATERIALS, 0.04)

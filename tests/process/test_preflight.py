"""Pre-flight guards (calendaring.process.preflight): a run that would not fit the machine is
refused before anything is allocated, with the estimate and the limit in the message."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calendaring.core.config import load_preset, with_overrides
from calendaring.process.electrode import recipe
from calendaring.process.preflight import ResourceError, check, estimate


def test_particle_counts_follow_the_mass_balance():
    cfg = load_preset("sweep")
    est = estimate(cfg)
    rec = recipe(cfg, np.random.default_rng(3))
    for name, n in rec.counts.items():
        assert est.particles[name] == pytest.approx(n, rel=0.08)
    big = estimate(with_overrides(cfg, {"domain.cell_x": 90e-6, "domain.cell_y": 90e-6}))
    assert big.n_particles == pytest.approx(9 * est.n_particles, rel=1e-9)  # area x 9


def test_calendering_steps_scale_with_stroke_over_speed():
    cfg = load_preset("sweep")
    a = estimate(cfg)
    b = estimate(with_overrides(cfg, {"protocol.inertial_number":
                                      cfg.protocol.inertial_number / 4}))
    assert b.plate_speed == pytest.approx(a.plate_speed / 4, rel=1e-9)
    assert b.steps["calender"] == pytest.approx(4 * a.steps["calender"], rel=1e-9)
    assert a.steps["calender"] == pytest.approx(cfg.protocol.stroke / (a.plate_speed * a.dt))


def test_a_cell_beyond_memory_is_refused_with_the_estimate():
    cfg = with_overrides(load_preset("sweep"), {"domain.cell_x": 0.05, "domain.cell_y": 0.05})
    with pytest.raises(ResourceError, match=r"memory: the run would need ~[\d.e+]+ GB .*"
                                            r"particles in a 0.05 x 0.05 m cell.*available"):
        check(cfg)
    est = check(load_preset("tiny"))  # the tiny preset fits any machine that runs the tests
    with pytest.raises(ResourceError, match="memory"):
        check(load_preset("tiny"), memory=0.5 * est.memory_bytes)


def test_a_pool_beyond_memory_is_refused():
    cfg = with_overrides(load_preset("tiny"), {"breakage.pool_capacity": 10**13})
    with pytest.raises(ResourceError, match="1e\\+13 pool slots"):
        check(cfg)


def test_billions_of_steps_are_refused():
    cfg = with_overrides(load_preset("tiny"), {"numerics.timestep_fraction": 1e-8})
    with pytest.raises(ResourceError, match=r"time steps: the run would need .* steps"):
        check(cfg)
    slow = with_overrides(load_preset("tiny"), {"protocol.plate_speed": 1e-9})
    with pytest.raises(ResourceError, match="calender"):
        check(slow)


def test_wall_time_beyond_the_limit_is_refused():
    cfg = load_preset("sweep")
    est = check(cfg)
    assert 0 < est.wall_seconds < math.inf
    with pytest.raises(ResourceError, match=r"wall time: .* allowed <= --max-hours"):
        check(cfg, max_hours=0.5 * est.wall_seconds / 3600)
    assert "estimate:" in est.line() and "particles" in est.line()
